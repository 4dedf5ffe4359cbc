import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pipeline.errors import AssetError, ConfigError, ShapeError
from pipeline.io import read_image, read_mask, write_image, write_json, write_mask


@dataclass(frozen=True)
class _Result:
    loss: float
    names: tuple[str, ...]


def test_write_json_converts_and_creates_dirs(tmp_path):
    path = tmp_path / "a" / "b" / "result.json"
    write_json(
        path,
        {
            "T": torch.eye(2, dtype=torch.float64),
            "arr": np.array([1.5, 2.0], np.float32),
            "n": np.int64(3),
            "x": 1 / 3,
            "tiny": 1.234567890123456e-9,
            "bad": [math.nan, math.inf],
            "flag": True,
            "path": Path("x/y.png"),
            "result": _Result(loss=0.25, names=("a", "b")),
        },
    )
    data = json.loads(path.read_text())
    assert data["T"] == [[1.0, 0.0], [0.0, 1.0]]
    assert data["arr"] == [1.5, 2.0]
    assert data["n"] == 3 and data["flag"] is True
    assert data["x"] == 0.3333333333
    assert data["tiny"] == pytest.approx(1.23456789e-9, rel=1e-9)
    assert data["bad"] == [None, None]
    assert data["path"] == "x/y.png"
    assert data["result"] == {"loss": 0.25, "names": ["a", "b"]}
    assert [p.name for p in path.parent.iterdir()] == ["result.json"]  # no temporary left behind


def test_write_json_rejects_unknown_types(tmp_path):
    with pytest.raises(ConfigError, match="cannot write a object as JSON"):
        write_json(tmp_path / "x.json", {"a": object()})


def test_mask_roundtrip(tmp_path):
    mask = np.zeros((5, 7), bool)
    mask[1:3, 2:6] = True
    path = tmp_path / "out" / "mask.png"
    write_mask(path, mask)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and set(np.unique(raw)) == {0, 255}
    np.testing.assert_array_equal(read_mask(path), mask)
    np.testing.assert_array_equal(read_mask(path, image_size=(5, 7)), mask)


def test_read_mask_threshold_and_colour(tmp_path):
    grey = np.array([[0, 127, 128, 255]], np.uint8)
    path = tmp_path / "m.png"
    cv2.imwrite(str(path), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    np.testing.assert_array_equal(read_mask(path), [[False, False, True, True]])


def test_read_mask_errors(tmp_path):
    with pytest.raises(AssetError, match="mask file not found: .*missing.png"):
        read_mask(tmp_path / "missing.png")
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"not an image")
    with pytest.raises(AssetError, match="cannot read mask file .*junk.png"):
        read_mask(junk)
    path = tmp_path / "m.png"
    write_mask(path, np.ones((4, 6), bool))
    with pytest.raises(ConfigError, match="is 6x4 but expected 8x5"):
        read_mask(path, image_size=(5, 8))


def test_write_mask_rejects_non_bool(tmp_path):
    with pytest.raises(ShapeError, match=r"mask: expected an \(H, W\) bool array .*got uint8"):
        write_mask(tmp_path / "m.png", np.zeros((3, 3), np.uint8))


def test_image_roundtrip(tmp_path):
    image = np.random.default_rng(0).integers(0, 255, (6, 8, 3), dtype=np.uint8)
    path = tmp_path / "img.png"
    write_image(path, image)
    out = read_image(path)
    assert out.shape == (6, 8, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, image)
    write_image(path, image[..., 0])
    assert read_image(path).shape == (6, 8, 3)  # grey read as 3 channels
    with pytest.raises(AssetError, match="image file not found"):
        read_image(tmp_path / "nope.jpg")
    with pytest.raises(ShapeError, match="uint8"):
        write_image(path, image.astype(np.float32))


# ---------------------------------------------------------------------------------------------------------------
# joints CSV (track pose --joints-csv)


def test_joints_csv_rows_by_frame_and_interpolation_against_a_naive_line(tmp_path):
    from pipeline.io import read_joints_csv

    path = tmp_path / "j.csv"
    path.write_text("time_s,frame,a,b\n0.4,4,1.0,-2.0\n0.0,0,0.0,0.0\n\n1.0,10,3.0,1.0\n")  # any row order
    table = read_joints_csv(path)
    assert table.names == ("a", "b") and table.frames.tolist() == [0, 4, 10]
    assert table.readings(4) == {"a": 1.0, "b": -2.0}
    with pytest.raises(ConfigError, match=r"j.csv: no row for frame 2 .*--interpolate-joints"):
        table.readings(2)
    by_frame = table.readings(7, interpolate=True)  # halfway from frame 4 to 10
    assert by_frame == pytest.approx({"a": 1.0 + 0.5 * 2.0, "b": -2.0 + 0.5 * 3.0})
    by_time = table.readings(7, 0.55, interpolate=True)  # a quarter of the way by time (0.4 -> 1.0)
    assert by_time == pytest.approx({"a": 1.0 + 0.25 * 2.0, "b": -2.0 + 0.25 * 3.0})
    with pytest.raises(ConfigError, match="frame 11 is outside the rows' frames 0-10"):
        table.readings(11, interpolate=True)


@pytest.mark.parametrize("text, message", [
    ("a,b\n1,2\n", "no 'frame' column"),
    ("frame,a,a\n0,1,2\n", "named once each"),
    ("frame,a\n", "at least 1 row"),
    ("frame,a\n0,1\n1\n", "line 3: expected 2 fields"),
    ("frame,a\n0,1\n1,x\n", "line 3, column a: expected a finite number, got 'x'"),
    ("frame,a\n0,1\n1,nan\n", "line 3, column a: expected a finite number, got 'nan'"),
    ("frame,a\n0.5,1\n", "line 2, column frame: expected a frame index"),
    ("frame,a\n0,1\n0,2\n", "frame 0 has more than one row"),
    ("frame,time_s,a\n0,1.0,1\n1,0.5,2\n", "time_s: expected times increasing"),
])
def test_joints_csv_errors_name_line_and_column(tmp_path, text, message):
    from pipeline.io import read_joints_csv

    path = tmp_path / "j.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        read_joints_csv(path)


def test_joints_csv_missing_file_is_an_asset_error(tmp_path):
    from pipeline.errors import AssetError
    from pipeline.io import read_joints_csv

    with pytest.raises(AssetError, match="joints CSV not found"):
        read_joints_csv(tmp_path / "none.csv")
