"""The manipulator pose demo on the bundled example (data/toy_arm)."""

import json

import pytest

from pipeline.demo.pose import EXAMPLE_DIR, demo_pose
from pipeline.pose_estimation import PoseFitConfig
from pipeline.segment import FileSegmenterConfig


@pytest.mark.slow
def test_demo_pose_writes_outputs_and_measures_errors(tmp_path):
    # the example's exact mask through the file segmenter (the ONNX path is tested with the demo command), half the work
    exact = FileSegmenterConfig(pattern=str(EXAMPLE_DIR / "mask.png"))
    errors = demo_pose(tmp_path, config=PoseFitConfig(iterations=250, working_max_side=320), segmenter=exact)
    assert errors["mask_iou"] == 1.0 and errors["segmenter"] == "FileSegmenterConfig"
    assert errors["end_effector_2d_px"] < 5.0 and errors["end_effector_3d_mm"] < 30.0, errors
    assert errors["rotation_deg"] < 3.0 and errors["primitive"] == "cad"
    result = json.loads((tmp_path / "result.json").read_text())
    truth = json.loads((EXAMPLE_DIR / "truth.json").read_text())
    assert result["image_size"] == {"width": 800, "height": 600} and result["root"] == truth["root"]
    for name in ("overlay.png", "history.png"):
        assert (tmp_path / name).stat().st_size > 0
