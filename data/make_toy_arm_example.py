"""Write the bundled synthetic manipulator example into data/toy_arm/ (deterministic: a fixed seed).

Run from the repository root: ``python data/make_toy_arm_example.py``. The example robot's CAD model
(``models/robots/toy_arm_mesh``) is drawn at random joint readings from a random viewpoint through an 800x600
camera with lens distortion; the files are what a user of ``pipeline pose`` has:

- ``image.png``: the shaded robot on clutter (BGR, distorted like a real lens);
- ``mask.png``: its exact robot mask (uint8 0/255, distorted the same way);
- ``camera.json``: the camera (project format, with its distortion coefficients);
- ``joints.json``: the joint readings ``{"name": value}`` (rad, m);
- ``truth.json``: ``T_cam_root`` of the root link ``base_link`` (4x4, metres, camera frame without distortion), the
  URDF and root used, and the end-effector (``tcp`` frame origin) in the camera frame (m) and in the image (px).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from pipeline.camera import Camera, save_camera  # noqa: E402
from pipeline.io import write_image, write_json, write_mask  # noqa: E402
from pipeline.robots import load_urdf_robot  # noqa: E402
from pipeline.synth.pose import distort_image, random_view, render_robot_image  # noqa: E402

OUT = REPO / "data" / "toy_arm"
URDF = "models/robots/toy_arm_mesh/toy_arm_mesh.urdf"
ROOT, TCP = "base_link", "tcp"
SEED = 11
CAMERA = Camera(K=((700.0, 0.0, 402.0), (0.0, 700.0, 296.0), (0.0, 0.0, 1.0)), width=800, height=600,
                dist=(-0.12, 0.06, 0.0005, -0.0003, 0.0))


def main() -> None:
    model = load_urdf_robot(REPO / URDF, ROOT, primitive="cad")
    rng = np.random.default_rng(SEED)
    joint_angles, T_cam_root = random_view(model, CAMERA, rng, fill_range=(0.6, 0.75))
    image, mask = render_robot_image(model, joint_angles, T_cam_root, CAMERA, rng)
    image, mask = distort_image(image, CAMERA), distort_image(mask, CAMERA, is_mask=True)
    T_root_tcp = model.link_frames_in_root(torch.from_numpy(joint_angles)[None])[0, model.frame_index(TCP)].numpy()
    tcp_cam = (T_cam_root @ T_root_tcp)[:3, 3]
    tcp_px, _ = cv2.projectPoints(tcp_cam[None], np.zeros(3), np.zeros(3), CAMERA.K_array(), CAMERA.dist_array())
    OUT.mkdir(parents=True, exist_ok=True)
    write_image(OUT / "image.png", image)
    write_mask(OUT / "mask.png", mask)
    save_camera(CAMERA, OUT / "camera.json")
    write_json(OUT / "joints.json", dict(zip(model.joint_names, joint_angles.tolist())))
    write_json(OUT / "truth.json", {
        "urdf": URDF,
        "root": ROOT,
        "T_cam_root": T_cam_root,
        "point_frame": TCP,
        "point_cam_m": tcp_cam,
        "point_px": tcp_px.reshape(2),
        "seed": SEED,
    })  # fmt: skip
    print(f"wrote {OUT}: {int(mask.sum())} robot pixels of {mask.size}")


if __name__ == "__main__":
    main()
