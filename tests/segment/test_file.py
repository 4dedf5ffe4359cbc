import numpy as np
import pytest

from pipeline.errors import AssetError, ConfigError
from pipeline.io import write_mask
from pipeline.segment import FileSegmenter, FileSegmenterConfig, make_segmenter


def test_pattern_reads_the_mask_of_each_frame(tmp_path):
    masks = []
    for frame in range(3):
        mask = np.zeros((6, 8), bool)
        mask[frame : frame + 2, 1:4] = True
        write_mask(tmp_path / "masks" / f"{frame:05d}.png", mask)
        masks.append(mask)
    config = FileSegmenterConfig(pattern=str(tmp_path / "masks" / "{frame:05d}.png"))
    assert config.per_frame
    segmenter = make_segmenter(config)
    assert isinstance(segmenter, FileSegmenter)
    image = np.zeros((6, 8, 3), np.uint8)
    for frame in (2, 0, 1):
        np.testing.assert_array_equal(segmenter(image, frame_index=frame), masks[frame])
    with pytest.raises(AssetError, match="mask file not found: .*00007.png"):
        segmenter(image, frame_index=7)


def test_single_path_serves_every_frame_and_checks_size(tmp_path):
    mask = np.eye(5, dtype=bool)
    write_mask(tmp_path / "m.png", mask)
    segmenter = FileSegmenter(FileSegmenterConfig(pattern=str(tmp_path / "m.png")))
    assert not segmenter.config.per_frame
    np.testing.assert_array_equal(segmenter(np.zeros((5, 5, 3), np.uint8), frame_index=9), mask)
    with pytest.raises(ConfigError, match="is 5x5 but expected 6x5"):
        segmenter(np.zeros((5, 6, 3), np.uint8))


def test_bad_patterns():
    with pytest.raises(ConfigError, match=r"unknown field\(s\) 'index'; the only field is \{frame\}"):
        FileSegmenterConfig(pattern="masks/{index}.png")
    with pytest.raises(ConfigError, match="not a valid mask pattern"):
        FileSegmenterConfig(pattern="masks/{frame.png")
    with pytest.raises(ConfigError, match="not a valid mask pattern"):
        FileSegmenterConfig(pattern="masks/{frame:q}.png")
    with pytest.raises(ConfigError, match="expected a mask path or pattern"):
        FileSegmenterConfig(pattern="")
    assert FileSegmenterConfig(pattern="a{{b}}/{frame:03d}.png").path(4) == "a{b}/004.png"
