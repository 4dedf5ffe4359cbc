"""Synthetic soft-arm cases shared by the shape benchmarks: a random arm, its image and exact mask, its truth.

Set-up of the acceptance criterion: 1280x720 image, fx = fy = 700 px, principal point at the centre, a 200 mm arm
(radius 14 mm at the base, 6 mm at the tip, linear in arc length) whose centreline's centroid is 0.4 m from the
camera, drawn whole in the image with its base nearer the image border (``pipeline.synth.soft_arm``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.camera import Camera  # noqa: E402
from pipeline.robots import ContinuumRobot  # noqa: E402
from pipeline.shapes.polyline import bezier_centerline  # noqa: E402
from pipeline.synth.soft_arm import pcc_arm, random_bezier_arm, render_tube_image  # noqa: E402

H, W = 720, 1280
K = np.array([[700.0, 0.0, (W - 1) / 2], [0.0, 700.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
CAMERA = Camera(K=K.tolist(), width=W, height=H)
LENGTH_M, BASE_RADIUS_M, TIP_RADIUS_M, DISTANCE_M = 0.2, 0.014, 0.006, 0.4

#: Kinds of arm: a random quadratic Bezier, a cubic that may bend both ways (an S), two constant-curvature arcs.
KINDS = ("quadratic", "cubic_s", "pcc")


@dataclass(frozen=True)
class ShapeCase:
    seed: int
    kind: str
    image: np.ndarray  # (H, W, 3) uint8 BGR
    mask: np.ndarray  # (H, W) bool
    truth_cam_m: np.ndarray  # (201, 3) centreline, uniform in arc length, base to tip


def make_case(seed: int, kind: str = "quadratic") -> ShapeCase:
    """One synthetic arm of ``kind`` from ``numpy.random.default_rng(seed)``."""
    rng = np.random.default_rng(seed)
    if kind == "quadratic":
        control = random_bezier_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, order=2)
        truth = bezier_centerline(control, 201)
    elif kind == "cubic_s":
        control = random_bezier_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, order=3,
                                    max_bend_rad=3.0)
        truth = bezier_centerline(control, 201)
    elif kind == "pcc":
        truth = pcc_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, n_segments=2, n_points=201)
    else:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    radii = np.linspace(BASE_RADIUS_M, TIP_RADIUS_M, len(truth))
    image, mask = render_tube_image(truth, radii, K, (H, W), rng)
    return ShapeCase(seed=seed, kind=kind, image=image, mask=mask, truth_cam_m=truth)


def robot(order: int = 2) -> ContinuumRobot:
    """The arm as the user describes it: length, radii and the Bezier order of the fit."""
    return ContinuumRobot(length_m=LENGTH_M, base_radius_m=BASE_RADIUS_M, tip_radius_m=TIP_RADIUS_M, order=order)
