import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from pipeline.cli._segmenter_args import add_segmenter_arguments, segmenter_config_from_args, segmenter_from_args
from pipeline.errors import ConfigError
from pipeline.io import read_mask, write_mask
from pipeline.segment import (
    AutoSegmenterConfig,
    ColorSegmenter,
    ColorSegmenterConfig,
    FileSegmenterConfig,
    OnnxSegmenterConfig,
    color_preset,
)

DATA = Path(__file__).resolve().parents[2] / "data" / "soft_arm" / "quadratic"


def parse(*argv, default="onnx"):
    parser = argparse.ArgumentParser()
    add_segmenter_arguments(parser, default=default)
    return parser.parse_args(argv)


def test_options_to_configs():
    assert segmenter_config_from_args(parse()) == OnnxSegmenterConfig()
    assert segmenter_config_from_args(parse(default="color")) == color_preset("soft_arm")
    args = parse("--segmenter", "onnx", "--onnx-model", "m/model.onnx", "--onnx-device", "cpu", "--onnx-threads", "2")
    assert segmenter_config_from_args(args) == OnnxSegmenterConfig(model="m/model.onnx", device="cpu", num_threads=2)
    args = parse("--all-components")
    assert segmenter_config_from_args(args) == OnnxSegmenterConfig(largest_component=False)
    args = parse("--segmenter", "color", "--hsv-lower", "170,100,50", "--hsv-upper", "10,255,255", "--open-px", "0",
                 "--all-components")  # fmt: skip
    assert segmenter_config_from_args(args) == ColorSegmenterConfig(
        hsv_lower=(170, 100, 50), hsv_upper=(10, 255, 255), open_px=0, largest_component=False
    )
    args = parse("--segmenter", "color", "--hsv-preset", "green", "--close-px", "7")
    assert segmenter_config_from_args(args) == color_preset("green", close_px=7)
    args = parse("--segmenter", "file", "--mask-pattern", "masks/{frame:05d}.png")
    assert segmenter_config_from_args(args) == FileSegmenterConfig(pattern="masks/{frame:05d}.png")
    assert isinstance(segmenter_from_args(parse(default="color")), ColorSegmenter)
    assert segmenter_config_from_args(parse(default="auto")) == AutoSegmenterConfig()
    args = parse("--segmenter", "auto", "--refine-band-px", "4", "--onnx-threads", "1", "--all-components",
                 "--refine-iterations", "5")
    assert segmenter_config_from_args(args) == AutoSegmenterConfig(band_px=4, num_threads=1, largest_component=False,
                                                                   iterations=5)
    args = parse("--segmenter", "auto", "--onnx-max-side", "640")
    assert segmenter_config_from_args(args) == AutoSegmenterConfig(max_side=640)
    assert segmenter_config_from_args(args).network().max_side == 640
    assert segmenter_config_from_args(parse("--onnx-max-side", "0")) == OnnxSegmenterConfig(max_side=0)


@pytest.mark.parametrize(
    "argv, message",
    [
        (("--segmenter", "onnx", "--hsv-preset", "red"), "--hsv-preset is an option of --segmenter color, but "),
        (("--segmenter", "color", "--onnx-model", "x"), "--onnx-model is an option of --segmenter onnx"),
        (("--segmenter", "color", "--mask-pattern", "x.png"), "--mask-pattern is an option of --segmenter file"),
        (("--segmenter", "color", "--hsv-lower", "1,2,3"), "--hsv-lower and --hsv-upper go together"),
        (("--segmenter", "color", "--hsv-preset", "red", "--hsv-lower", "1,2,3", "--hsv-upper", "4,5,6"),
         "either --hsv-preset or --hsv-lower/--hsv-upper"),
        (("--segmenter", "color", "--hsv-lower", "1,2", "--hsv-upper", "4,5,6"), "--hsv-lower: expected H,S,V"),
        (("--segmenter", "file",), "--segmenter file needs --mask-pattern"),
        (("--segmenter", "onnx", "--refine-band-px", "3"), "--refine-band-px is an option of --segmenter auto, but "),
        (("--segmenter", "auto", "--refine-band-px", "0"), "band_px: expected an int >= 1"),
        (("--segmenter", "onnx", "--refine-iterations", "5"), "--refine-iterations is an option of --segmenter auto"),
        (("--segmenter", "auto", "--refine-iterations", "0"), "iterations: expected an int >= 1"),
        (("--segmenter", "color", "--hsv-preset", "teal"), "unknown colour preset 'teal'"),
        (("--segmenter", "color", "--onnx-max-side", "640"), "--onnx-max-side is an option of --segmenter onnx and auto"),
        (("--segmenter", "onnx", "--onnx-max-side", "-1"), r"max_side: expected an int >= 0"),
    ],
)  # fmt: skip
def test_bad_option_combinations(argv, message):
    with pytest.raises(ConfigError, match=message):
        segmenter_config_from_args(parse(*argv))


def test_segment_in_process_with_file_pattern_and_overlay(tmp_path, capsys):
    mask = read_mask(DATA / "mask.png")
    write_mask(tmp_path / "masks" / "003.png", mask)
    out, overlay = tmp_path / "out.png", tmp_path / "overlay.png"
    pattern = str(tmp_path / "masks" / "{frame:03d}.png")
    argv = ["segment", "--image", str(DATA / "image.png"), "--segmenter", "file", "--frame", "3",
            "--mask-pattern", pattern, "--out", str(out), "--overlay", str(overlay)]  # fmt: skip
    assert main(argv) == 0
    np.testing.assert_array_equal(read_mask(out), mask)
    assert overlay.is_file()
    assert f"{int(mask.sum())} robot pixels" in capsys.readouterr().out
    argv[argv.index("--frame") + 1] = "4"
    assert main(argv) == 2
    assert "mask file not found" in capsys.readouterr().err


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "pipeline", "segment", *args], capture_output=True, text=True,
                          timeout=120)  # fmt: skip


def test_segment_command_colour_success(tmp_path):
    out = tmp_path / "mask.png"
    proc = run_cli("--image", str(DATA / "image.png"), "--segmenter", "color", "--out", str(out),
                   "--overlay", str(tmp_path / "overlay.png"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "robot pixels" in proc.stdout
    mask, truth = read_mask(out), read_mask(DATA / "mask.png")
    assert (mask & truth).sum() / (mask | truth).sum() > 0.95
    assert (tmp_path / "overlay.png").is_file()


def test_segment_command_bad_input_exits_2(tmp_path):
    proc = run_cli("--image", str(tmp_path / "missing.png"), "--out", str(tmp_path / "m.png"))
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: image file not found") and proc.stderr.count("\n") == 1
    proc = run_cli("--image", str(DATA / "image.png"), "--out", str(tmp_path / "m.png"), "--onnx-model", "nope")
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: ONNX model file not found") and proc.stderr.count("\n") == 1
    assert "Traceback" not in proc.stderr and not (tmp_path / "m.png").exists()
