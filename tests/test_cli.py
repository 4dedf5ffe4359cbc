import json
import subprocess
import sys

import pytest

from pipeline import __version__
from pipeline.cli import COMMAND_MODULES, main

CAMERA = {"K": [[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]], "dist": [], "width": 640, "height": 480}


def run_module(*args):
    return subprocess.run([sys.executable, "-m", "pipeline", *args], capture_output=True, text=True, timeout=60)


@pytest.fixture
def camera_file(tmp_path):
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(CAMERA))
    return path


def test_help_lists_commands():
    proc = run_module("--help")
    assert proc.returncode == 0
    for name in COMMAND_MODULES:
        assert name in proc.stdout


def test_version():
    proc = run_module("--version")
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"pipeline {__version__}"


def test_bad_camera_file_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "cam.json"
    bad.write_text('{"K": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "width": 10}')
    proc = run_module("camera", "--camera", str(bad))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1
    assert proc.stderr.startswith("error: ") and "missing key 'height'" in proc.stderr
    assert "Traceback" not in proc.stderr


def test_unknown_command_exits_2(capsys):
    assert main(["bogus"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "invalid choice: 'bogus'" in err and err.count("\n") == 1


def test_usage_errors_exit_2(capsys, tmp_path):
    assert main([]) == 2
    assert "no command given" in capsys.readouterr().err
    assert main(["camera"]) == 2
    assert capsys.readouterr().err == "error: pipeline camera: the following arguments are required: --camera\n"
    assert main(["camera", "--camera", str(tmp_path / "missing.json")]) == 2
    assert "camera file not found" in capsys.readouterr().err


def test_camera_prints_and_resizes(camera_file, tmp_path, capsys):
    assert main(["camera", "--camera", str(camera_file)]) == 0
    assert json.loads(capsys.readouterr().out) == CAMERA
    out = tmp_path / "out" / "small.json"
    assert main(["camera", "--camera", str(camera_file), "--resize", "320x240", "--out", str(out)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text())
    assert printed["width"] == 320 and printed["height"] == 240
    assert printed["K"] == [[250.0, 0.0, 159.5], [0.0, 250.0, 119.5], [0.0, 0.0, 1.0]]
    assert main(["camera", "--camera", str(camera_file), "--max-side", "320"]) == 0
    assert json.loads(capsys.readouterr().out) == printed


def test_camera_bad_resize(camera_file, capsys):
    assert main(["camera", "--camera", str(camera_file), "--resize", "320by240"]) == 2
    assert "--resize: expected WIDTHxHEIGHT" in capsys.readouterr().err
