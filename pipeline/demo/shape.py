"""End-to-end demos on the bundled examples (``data/``, in the repository checkout): run, write pictures, score."""

from __future__ import annotations

import json
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "data"


def demo_shape(out_dir: Path, example: Path = DATA / "soft_arm" / "quadratic", *, segmenter=None) -> dict:
    """Reconstruct a bundled soft-arm example from its RGB image and score it against its truth.

    Reads ``example/{image.png, mask.png, camera.json, truth.json}`` (the robot's length, radii and order come from
    the truth file), segments the image with ``segmenter`` (a ``pipeline.segment`` config; default: the colour
    segmenter's ``soft_arm`` preset), runs ``reconstruct_shape`` on that mask with the default ``ShapeFitConfig`` at the truth's order,
    and writes ``mask.png`` (the segmenter's), ``result.json``, ``overlay.png`` (the fitted outline, centreline and
    keypoints on the undistorted image) and ``history.png`` into ``out_dir``. The example's own ``mask.png`` (the
    true silhouette) only scores the segmentation.

    Returns:
        ``pipeline.evaluate.centerline_errors`` of the estimate against the truth (``mean_2d_px``,
        ``mean_3d_mm``, ...) plus ``segmenter``, ``mask_iou`` (segmented mask against the true one),
        ``seconds`` and ``loss``.
    """
    import numpy as np

    from pipeline.camera import load_camera, undistort_image
    from pipeline.evaluate import centerline_errors, mask_iou
    from pipeline.io import read_image, read_mask, write_image, write_json, write_mask
    from pipeline.robots import ContinuumRobot
    from pipeline.segment import color_preset, make_segmenter
    from pipeline.shape_estimation import ShapeFitConfig, draw_shape_overlay, reconstruct_shape
    from pipeline.viz import plot_history

    out_dir = Path(out_dir)
    camera = load_camera(example / "camera.json")
    truth = json.loads((example / "truth.json").read_text(encoding="utf-8"))
    robot = ContinuumRobot(length_m=truth["length_m"], base_radius_m=truth["base_radius_m"],
                           tip_radius_m=truth["tip_radius_m"])
    segmenter = color_preset("soft_arm") if segmenter is None else segmenter
    raw_image = read_image(example / "image.png")
    mask = make_segmenter(segmenter)(raw_image)
    true_mask = read_mask(example / "mask.png", camera.image_size)
    iou = mask_iou(mask, true_mask)
    write_mask(out_dir / "mask.png", mask)
    result = reconstruct_shape(mask, robot, camera, ShapeFitConfig(order=truth.get("order", 2)))
    errors = centerline_errors(result.centerline_cam_m, np.asarray(truth["centerline_cam_m"]), result.camera.K_array())
    errors.update(segmenter=type(segmenter).__name__, mask_iou=iou, seconds=result.seconds, loss=result.loss)
    write_json(out_dir / "result.json", {**result.to_dict(), "errors": errors})
    image = undistort_image(raw_image, camera)[0]
    write_image(out_dir / "overlay.png", draw_shape_overlay(image, result, robot))
    write_image(out_dir / "history.png", plot_history(result.history, title="shape loss", best_start=result.best_start))
    return errors
