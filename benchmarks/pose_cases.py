"""Synthetic pose cases shared by the pose benchmarks (acceptance_pose, ablation_losses, bench_pose).

A case is the example robot (``models/robots/toy_arm``) at random joint readings seen from a random viewpoint
through a 640x480 camera (f = 600 px), its exact mask rendered from the primitives (``collision``) or from the CAD
meshes (``toy_arm_mesh``, ``cad``), optionally corrupted like a segmenter's mask. Seeds make every case exact.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.camera import Camera  # noqa: E402
from pipeline.evaluate import point_errors, pose_errors  # noqa: E402
from pipeline.robots.manipulator import ManipulatorModel, load_urdf_robot  # noqa: E402
from pipeline.synth.pose import corrupt_mask, random_view, render_robot_mask  # noqa: E402

CAMERA = Camera(K=((600.0, 0.0, 319.5), (0.0, 600.0, 239.5), (0.0, 0.0, 1.0)), width=640, height=480)
URDF = {"primitives": REPO / "models/robots/toy_arm/toy_arm.urdf",
        "cad": REPO / "models/robots/toy_arm_mesh/toy_arm_mesh.urdf"}
TRUTH_PRIMITIVE = {"primitives": "collision", "cad": "cad"}
POINT_FRAME = "tcp"
NOISE_PX, BLOB_FRACTION = 1.0, 0.03


@dataclass(frozen=True)
class Case:
    name: str
    kind: str  # "clean" or "noisy" (boundary noise and a false-positive blob)
    joint_angles: np.ndarray  # (J,)
    T_cam_root: np.ndarray  # (4, 4)
    mask: np.ndarray  # (H, W) bool


def load_model(truth: str, primitive: str, primitive_size: str = "bbox") -> ManipulatorModel:
    """The robot of the ``truth`` kind ("primitives" or "cad") with the fit's link geometry."""
    return load_urdf_robot(URDF[truth], "base_link", primitive=primitive, primitive_size=primitive_size)


def make_cases(truth: str, count: int, seed0: int = 1000, corrupted_every: int = 2) -> list[Case]:
    """``count`` cases whose masks come from the ``truth`` geometry; every ``corrupted_every``-th one (the odd ones
    by default) has 1 px boundary noise and a false-positive blob of 3 % of the robot's area; 0 for none."""
    model = load_model(truth, TRUTH_PRIMITIVE[truth])
    cases = []
    for i in range(count):
        rng = np.random.default_rng(seed0 + i)
        q, T = random_view(model, CAMERA, rng)
        mask = render_robot_mask(model, q, T, CAMERA)
        noisy = corrupted_every > 0 and i % corrupted_every == corrupted_every - 1
        if noisy:
            mask = corrupt_mask(mask, rng, boundary_noise_px=NOISE_PX, blob_fraction=BLOB_FRACTION)
        cases.append(Case(f"{truth}-{seed0 + i}", "noisy" if noisy else "clean", q, T, mask))
    return cases


def point_root(model: ManipulatorModel, joint_angles: np.ndarray) -> np.ndarray:
    """``(3,)`` the end-effector point (``tcp`` frame origin) in the root frame."""
    T = model.link_frames_in_root(torch.from_numpy(joint_angles)[None])[0, model.frame_index(POINT_FRAME)]
    return T[:3, 3].numpy()


def case_errors(model: ManipulatorModel, case: Case, T_cam_root: np.ndarray) -> dict[str, float]:
    """End-effector 2D (px) / 3D (mm) errors and rotation (deg) / translation (mm) errors of one estimate."""
    point = point_errors(T_cam_root[None], case.T_cam_root[None], point_root(model, case.joint_angles)[None],
                         CAMERA.K_array())
    pose = pose_errors(T_cam_root[None], case.T_cam_root[None])
    return {"err_2d_px": float(point["err_2d_px"][0]), "err_3d_mm": float(point["err_3d_mm"][0]),
            "rotation_deg": float(pose["rotation_deg"][0]), "translation_mm": float(pose["translation_mm"][0])}


def load_average() -> str:
    """The 1-minute load average (other processes share the CPU; timings are noisy when it exceeds the cores)."""
    try:
        return Path("/proc/loadavg").read_text().split()[0]
    except OSError:
        return "?"
