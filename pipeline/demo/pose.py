"""Demo of the manipulator pose fit on the bundled example (``data/toy_arm``, written by
``data/make_toy_arm_example.py``): fit, write the result, an overlay and the loss history, and measure the errors
against the example's truth. Needs the repository checkout (the example and the robot live in ``data/`` and
``models/``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from pipeline.camera import load_camera
from pipeline.evaluate import mask_iou, point_errors, pose_errors
from pipeline.io import read_image, read_mask, write_image, write_json, write_mask
from pipeline.pose_estimation import PoseFitConfig, draw_pose_overlay, estimate_pose_from_readings, pose_result_json
from pipeline.robots.manipulator import load_urdf_robot
from pipeline.segment import OnnxSegmenterConfig, SegmenterConfig, make_segmenter
from pipeline.viz import draw_points, plot_history

__all__ = ["EXAMPLE_DIR", "demo_pose"]

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_DIR = REPO / "data" / "toy_arm"


def demo_pose(
    out_dir: Path,
    *,
    primitive: str = "cad",
    config: PoseFitConfig = PoseFitConfig(),
    segmenter: SegmenterConfig | None = None,
) -> dict:
    """Fit the bundled example from its RGB image and return its errors.

    The image is segmented by ``segmenter`` (default: the shipped ONNX model ``robot_deeplab``); the example's
    ``mask.png`` (the true silhouette) only scores that segmentation. Writes ``mask.png`` (the segmenter's),
    ``result.json`` (as ``pipeline pose`` does), ``overlay.png`` (the undistorted image with the fitted outline
    in green, the link frames, the true end effector in yellow) and ``history.png`` to ``out_dir``.

    Args:
        out_dir: output folder (created).
        primitive: link geometry of the fit (the example was drawn from the CAD meshes).
        config: fit settings.
        segmenter: a ``pipeline.segment`` config.

    Returns:
        ``{"end_effector_2d_px", "end_effector_3d_mm", "rotation_deg", "translation_mm", "mask_iou", "segmenter",
        "seconds", "loss", "primitive", "out_dir"}``: errors of the ``tcp`` frame origin in the image (px, input
        resolution) and in the camera frame (mm), and of ``T_cam_root``; IoU of the segmented mask.
    """
    out_dir = Path(out_dir)
    truth = json.loads((EXAMPLE_DIR / "truth.json").read_text())
    camera = load_camera(EXAMPLE_DIR / "camera.json")
    segmenter = OnnxSegmenterConfig() if segmenter is None else segmenter
    image = read_image(EXAMPLE_DIR / "image.png")
    mask = make_segmenter(segmenter)(image)
    true_mask = read_mask(EXAMPLE_DIR / "mask.png", camera.image_size)
    iou = mask_iou(mask, true_mask)
    write_mask(out_dir / "mask.png", mask)
    readings = json.loads((EXAMPLE_DIR / "joints.json").read_text())
    model = load_urdf_robot(REPO / truth["urdf"], truth["root"], primitive=primitive)
    result = estimate_pose_from_readings(mask, model, readings, camera, config)

    output = pose_result_json(result, model, camera)
    write_json(out_dir / "result.json", output)
    overlay = draw_pose_overlay(image, model, result, camera)
    true_point = np.asarray(truth["point_cam_m"], dtype=np.float64)  # drawn in the undistorted image
    overlay = draw_points(overlay, (true_point @ camera.K_array().T)[None, :2] / true_point[2], radius=3)
    write_image(out_dir / "overlay.png", overlay)
    write_image(out_dir / "history.png", plot_history(result.history, title="pose loss (toy_arm example)",
                                                      best_start=result.best_start))

    T_true = np.asarray(truth["T_cam_root"], dtype=np.float64)
    q = torch.from_numpy(result.joint_angles)[None]
    point_root = model.link_frames_in_root(q)[0, model.frame_index(truth["point_frame"]), :3, 3].numpy()
    point_err = point_errors(result.T_cam_root[None], T_true[None], point_root[None], camera.K_array())
    estimated_px = np.asarray(output["frames_px"][truth["point_frame"]])  # with the lens distortion
    pose_err = pose_errors(result.T_cam_root[None], T_true[None])
    return {
        "end_effector_2d_px": float(np.linalg.norm(estimated_px - np.asarray(truth["point_px"]))),
        "end_effector_3d_mm": float(point_err["err_3d_mm"][0]),
        "rotation_deg": float(pose_err["rotation_deg"][0]),
        "translation_mm": float(pose_err["translation_mm"][0]),
        "mask_iou": iou,
        "segmenter": type(segmenter).__name__,
        "seconds": result.seconds,
        "loss": result.loss,
        "primitive": primitive,
        "out_dir": str(out_dir),
    }
