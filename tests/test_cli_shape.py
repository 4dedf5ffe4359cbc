"""``pipeline shape``: bad input exits 2 with a message naming the problem; a run writes its result files."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.cli import main
from pipeline.io import write_mask

EXAMPLE = Path(__file__).resolve().parents[1] / "data" / "soft_arm" / "quadratic"
ARM = ["--length", "0.2", "--base-radius", "0.014", "--tip-radius", "0.006"]


def shape(*args):
    return main(["shape", "--camera", str(EXAMPLE / "camera.json"), *args])


def quick_colour_fit(image, tmp_path, capsys):
    """``shape --image`` of ``image`` (written to ``tmp_path``) with the colour segmenter and a small fit: its JSON."""
    cv2.imwrite(str(tmp_path / "image.png"), image)
    out = tmp_path / "r.json"
    code = shape("--image", str(tmp_path / "image.png"), *ARM, "--segmenter", "color", "--order", "2",
                 "--iterations", "30", "--starts", "2", "--max-side", "320", "--out", str(out))
    assert code == 0, capsys.readouterr().err
    return json.loads(out.read_text())


def error_line(capsys):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def test_empty_mask_exits_2(tmp_path, capsys):
    write_mask(tmp_path / "empty.png", np.zeros((360, 640), bool))
    assert shape("--mask", str(tmp_path / "empty.png"), *ARM) == 2
    assert "mask is empty" in error_line(capsys)


def test_an_image_the_segmenter_finds_nothing_in_names_the_segmenter_and_what_to_try(tmp_path, capsys):
    cv2.imwrite(str(tmp_path / "grey.png"), np.full((360, 640, 3), 128, np.uint8))  # no colour the preset keeps
    assert shape("--image", str(tmp_path / "grey.png"), *ARM, "--segmenter", "color") == 2
    err = error_line(capsys)
    assert "grey.png: the color segmenter found no robot pixel" in err and "--hsv-lower" in err, err


def test_mask_without_skeleton_path_exits_2(tmp_path, capsys):
    blob = np.zeros((360, 640), np.uint8)
    cv2.circle(blob, (320, 180), 6, 1, -1)  # a disk: its skeleton is one pixel
    write_mask(tmp_path / "blob.png", blob.astype(bool))
    assert shape("--mask", str(tmp_path / "blob.png"), *ARM, "--max-side", "640") == 2
    assert "skeleton has no path" in error_line(capsys)


def test_camera_not_matching_the_image_exits_2(tmp_path, capsys):
    small = cv2.resize(cv2.imread(str(EXAMPLE / "mask.png"), cv2.IMREAD_GRAYSCALE), (320, 180))
    cv2.imwrite(str(tmp_path / "small.png"), small)
    assert shape("--mask", str(tmp_path / "small.png"), *ARM) == 2
    assert "camera is 640x360 but image is 320x180" in error_line(capsys)
    assert shape("--image", str(tmp_path / "small.png"), *ARM) == 2
    assert "camera is 640x360 but image is 320x180" in error_line(capsys)


@pytest.mark.parametrize("radius", ["0", "-0.01"])
def test_non_positive_base_radius_exits_2(radius, capsys):
    args = ["--length", "0.2", "--base-radius", radius, "--tip-radius", "0.006"]
    assert shape("--mask", str(EXAMPLE / "mask.png"), *args) == 2
    assert "base radius must be > 0 m" in error_line(capsys)


def test_bad_base_pixel_and_missing_source_exit_2(capsys):
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--base-pixel", "12") == 2
    assert "--base-pixel: expected U,V" in error_line(capsys)
    assert shape(*ARM) == 2
    assert "one of the arguments --mask --image is required" in error_line(capsys)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--order", "cubic") == 2
    assert "--order: expected auto or an int >= 1" in error_line(capsys)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--order", "0") == 2
    assert "order: expected an int >= 1" in error_line(capsys)


def test_rim_offset_reaches_the_fit_and_a_bad_one_exits_2(capsys, monkeypatch):
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--rim-offset-px", "nan") == 2
    assert "rim_offset_px: expected a finite number" in error_line(capsys)
    import pipeline.shape_estimation as shape_estimation

    seen = []

    def record(mask, robot, camera, config, **kwargs):
        seen.append(config.rim_offset_px)
        raise shape_estimation.ShapeError("recorded")

    monkeypatch.setattr(shape_estimation, "reconstruct_shape", record)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--rim-offset-px", "1.5") == 2
    assert seen == [1.5] and "recorded" in error_line(capsys)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--rim-offset-px", "auto") == 2
    assert seen == [1.5, "auto"] and "recorded" in error_line(capsys)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--rim-offset-px", "wide") == 2
    assert "--rim-offset-px: expected a number of pixels, auto or image, got 'wide'" in error_line(capsys)
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--rim-offset-px", "image") == 2
    assert "--rim-offset-px image: reads the rim from the colour image; give --image" in error_line(capsys)
    # Left out: 0 with --mask (taken as exact), "image" with --image (a segmenter's rim read from the image, which
    # reaches the fit); given, as given.
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM) == 2
    assert seen[-1] == 0.0
    images = []
    monkeypatch.setattr(shape_estimation, "reconstruct_shape",
                        lambda mask, robot, camera, config, image=None, **kwargs: images.append(image) or record(
                            mask, robot, camera, config))
    assert shape("--image", str(EXAMPLE / "image.png"), *ARM, "--segmenter", "color") == 2
    assert seen[-1] == "image" and images[-1].shape == (360, 640, 3)
    assert shape("--image", str(EXAMPLE / "image.png"), *ARM, "--segmenter", "color", "--rim-offset-px", "0.5") == 2
    assert seen[-1] == 0.5


def test_fit_options_default_to_the_librarys(monkeypatch):
    """Left out, ``--max-side``, ``--iterations``, ``--starts`` and ``--seed`` give ``ShapeFitConfig``'s defaults
    (the CLI's own defaults do not drift from the library's); given, they reach the config."""
    import pipeline.shape_estimation as shape_estimation
    from pipeline.shape_estimation import ShapeFitConfig

    seen = []

    def record(mask, robot, camera, config, **kwargs):
        seen.append(config)
        raise shape_estimation.ShapeError("recorded")

    monkeypatch.setattr(shape_estimation, "reconstruct_shape", record)
    names = ("working_max_side", "iterations", "starts", "seed")
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM) == 2
    assert [getattr(seen[0], name) for name in names] == [getattr(ShapeFitConfig(), name) for name in names]
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--max-side", "320") == 2
    assert seen[1].working_max_side == 320
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--model", "pcc") == 2
    assert seen[2].pcc_start == ShapeFitConfig().pcc_start == "bezier"
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--model", "pcc", "--pcc-start", "hypotheses") == 2
    assert seen[3].pcc_start == "hypotheses"
    assert shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--model", "auto", "--section-lengths", "0.1,0.1") == 2
    assert seen[4].model == "auto" and seen[4].section_lengths_m == (0.1, 0.1) and seen[4].pcc_start == "bezier"


def test_bad_pcc_options_exit_2(capsys):
    mask = ["--mask", str(EXAMPLE / "mask.png"), *ARM]
    assert shape(*mask, "--model", "bezier", "--section-lengths", "0.1,0.1") == 2
    assert "--section-lengths is an option of --model pcc and auto, but --model is bezier" in error_line(capsys)
    assert shape(*mask, "--model", "pcc", "--section-lengths", "0.1,x") == 2
    assert "--section-lengths: expected L1,L2,... (numbers, metres)" in error_line(capsys)
    assert shape(*mask, "--model", "pcc", "--section-lengths", "0.1,0.1,0.0") == 2
    assert "section_lengths_m: expected 2 lengths > 0" in error_line(capsys)
    assert shape(*mask, "--model", "pcc", "--section-lengths", "0.05,0.05") == 2
    assert "section_lengths_m: they sum to 0.1 m, expected the robot's length 0.2 m" in error_line(capsys)
    assert shape(*mask, "--model", "pcc", "--sections", "0") == 2
    assert "sections: expected an int >= 1" in error_line(capsys)
    assert shape(*mask, "--model", "bezier", "--pcc-start", "hypotheses") == 2
    assert "--pcc-start is an option of --model pcc and auto, but --model is bezier" in error_line(capsys)
    assert shape(*mask, "--model", "auto", "--pcc-start", "hypotheses") == 2
    assert "pcc_start: model 'auto' refines the Bezier fit into sections, expected 'bezier'" in error_line(capsys)


def test_subprocess_exit_code_and_one_line(tmp_path):
    write_mask(tmp_path / "empty.png", np.zeros((360, 640), bool))
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", "shape", "--camera", str(EXAMPLE / "camera.json"), "--mask",
         str(tmp_path / "empty.png"), *ARM], capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ") and "mask is empty" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.slow
def test_mask_run_writes_result_overlay_and_history(tmp_path, capsys):
    out, overlay, history = tmp_path / "r.json", tmp_path / "o.png", tmp_path / "h.png"
    code = shape("--mask", str(EXAMPLE / "mask.png"), *ARM, "--model", "bezier", "--order", "2", "--iterations",
                 "30", "--starts", "2", "--max-side", "320", "--out", str(out), "--overlay", str(overlay),
                 "--history", str(history))
    assert code == 0, capsys.readouterr().err
    assert "shape: order 2, loss" in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert np.array(result["control_points_cam_m"]).shape == (3, 3)
    assert np.array(result["centerline_cam_m"]).shape == (101, 3)
    assert len(result["radii_m"]) == 100 and result["iterations"] == 30
    assert np.array(result["keypoints_px"]).shape == (4, 2)
    assert result["image_size"] == {"width": 640, "height": 360}
    assert result["camera"]["K"][0][0] == 520.0 and result["order"] == 2
    assert cv2.imread(str(overlay)).shape == (360, 640, 3)
    assert cv2.imread(str(history)) is not None


@pytest.mark.slow
def test_image_run_with_the_default_segmenter(tmp_path, capsys):
    out = tmp_path / "r.json"
    code = shape("--image", str(EXAMPLE / "image.png"), *ARM, "--iterations", "20", "--starts", "1",
                 "--max-side", "320", "--keypoint-mode", "endpoint", "--model", "bezier", "--out", str(out))
    assert code == 0, capsys.readouterr().err
    result = json.loads(out.read_text())
    assert result["keypoint_mode"] == "endpoint" and np.array(result["keypoints_px"]).shape == (1, 2)
    # The default order is auto: orders 2, 3, ... fitted in turn, the chosen one's control points written (the
    # Bezier fit's: with the default model the sections may be kept instead, whose result has one "order").
    fitted = sorted(result["order_losses"])
    assert fitted[:2] == ["2", "3"] and result["iterations"] == 20 + (6 + 100) * (len(fitted) - 1)  # 6 warm-up steps: 20 x 0.3
    assert np.array(result["control_points_cam_m"]).shape == (result["order"] + 1, 3)
    assert result["loss"] == result["order_losses"][str(result["order"])]
    assert result["input"]["image"].endswith("image.png")


@pytest.mark.slow
def test_a_clutter_blob_larger_than_the_arm_is_not_fitted(tmp_path, capsys):
    # The example image with a blob of the arm's colour, larger than the arm, painted where the arm is not: the
    # colour segmenter's largest component is the blob; the fit takes the component the arm's pre-fit explains best.
    image, truth = cv2.imread(str(EXAMPLE / "image.png")), cv2.imread(str(EXAMPLE / "mask.png"), 0) > 0
    rows, cols = np.nonzero(truth)
    far = (600, 60) if cols.mean() < 320 else (40, 60)  # a corner away from the arm
    radius = int(np.sqrt(1.5 * truth.sum() / np.pi))
    disc = np.zeros_like(truth, np.uint8)  # an ellipse of 1.5 times the arm's area (its skeleton is a segment)
    cv2.ellipse(disc, (far[0] if far[0] < 320 else far[0] - radius // 2, far[1] + radius // 2),
                (int(1.6 * radius), int(0.62 * radius)), 0, 0, 360, 1, -1)
    assert not (disc.astype(bool) & truth).any()
    image[disc > 0] = image[truth].reshape(-1, 3).mean(axis=0).astype(np.uint8)
    result = quick_colour_fit(image, tmp_path, capsys)
    assert result["arm_candidates"] == 2 and result["arm_candidate_losses"][1] < result["arm_candidate_losses"][0]
    K = np.array(result["camera"]["K"])
    centre = np.array(result["centerline_cam_m"]) @ K.T
    u, v = (centre[:, :2] / centre[:, 2:]).round().astype(int).T
    near = cv2.dilate(truth.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    inside = near[v.clip(0, truth.shape[0] - 1), u.clip(0, truth.shape[1] - 1)]
    assert inside.mean() > 0.9  # the arm was fitted, not the blob


@pytest.mark.slow
def test_an_arm_cut_by_a_band_in_front_of_it_is_fitted_whole(tmp_path, capsys):
    """The example image with a grey band across the middle of the arm: the colour segmenter's mask holds two pieces;
    ``shape --image`` segments with every component kept, the pieces are one candidate and the fit joins them (with
    the largest piece alone, as before session 29, the centreline covers about half the arm)."""
    image, truth = cv2.imread(str(EXAMPLE / "image.png")), cv2.imread(str(EXAMPLE / "mask.png"), 0) > 0
    rows, cols = np.nonzero(truth)
    vertical = rows.max() - rows.min() > cols.max() - cols.min()
    if vertical:  # a band across the arm's longer extent, at its middle, 8 px wide
        middle = int((rows.min() + rows.max()) / 2)
        image[middle - 4:middle + 4] = 128
    else:
        middle = int((cols.min() + cols.max()) / 2)
        image[:, middle - 4:middle + 4] = 128
    result = quick_colour_fit(image, tmp_path, capsys)
    K = np.array(result["camera"]["K"])
    centre = np.array(result["centerline_cam_m"]) @ K.T
    u, v = (centre[:, :2] / centre[:, 2:]).T
    along = v if vertical else u
    lo, hi = (rows.min(), rows.max()) if vertical else (cols.min(), cols.max())
    assert along.max() - along.min() > 0.8 * (hi - lo), (along.min(), along.max(), lo, hi)  # both pieces covered
