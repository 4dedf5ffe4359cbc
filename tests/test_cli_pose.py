"""``pipeline pose`` on the bundled example (data/toy_arm): outputs, and exit code 2 with one clear line on bad
input."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.cli import main
from pipeline.io import write_mask
from pipeline.pose_estimation import AMBIGUITY_LOSS_RATIO

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "data" / "toy_arm"
URDF = REPO / "models" / "robots" / "toy_arm_mesh" / "toy_arm_mesh.urdf"
JOINTS = json.loads((DATA / "joints.json").read_text())
BASE = ["pose", "--camera", str(DATA / "camera.json"), "--urdf", str(URDF), "--root", "base_link"]
QUICK = ["--iterations", "250", "--working-max-side", "320"]  # half the default work


def joints_arg(readings):
    return ",".join(f"{name}={value!r}" for name, value in readings.items())


def expect_error(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, err
    return err


@pytest.mark.slow
def test_pose_writes_result_overlay_and_history(tmp_path):
    out, overlay, history = tmp_path / "result.json", tmp_path / "overlay.png", tmp_path / "history.png"
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline", *BASE, "--joints-file", str(DATA / "joints.json"),
         "--mask", str(DATA / "mask.png"), "--primitive", "cad", *QUICK, "--out", str(out),
         "--overlay", str(overlay), "--history", str(history)],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith(f"{out}: T_cam_root t = (")
    result = json.loads(out.read_text())
    T = np.array(result["T_cam_root"])
    assert T.shape == (4, 4) and np.isfinite(T).all()
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    for key in ("root", "loss", "iterations", "seconds", "starts_final_loss", "joints", "primitive", "image_size",
                "working_size", "frames_cam_m", "frames_px", "best_start", "attempts", "loss_before_polish", "ambiguous",
                "runner_up", "robot", "boundary_offset_px", "weight_hidden"):
        assert key in result
    assert result["weight_hidden"] in (1.0, 0.25)
    assert isinstance(result["ambiguous"], bool)
    if result["runner_up"] is not None:  # some start ended > 20 degrees away: its pose, loss and angle are reported
        runner = result["runner_up"]
        assert runner["rotation_deg"] > 20 and np.array(runner["T_cam_root"]).shape == (4, 4)
        if runner["start"] is not None:
            assert runner["loss_ratio"] == pytest.approx(runner["loss"] / result["starts_final_loss"][result["best_start"]])
        assert result["ambiguous"] == (runner["loss_ratio"] <= AMBIGUITY_LOSS_RATIO)
    assert result["loss"] <= result["loss_before_polish"]
    assert result["root"] == "base_link" and result["primitive"] == "cad" and result["iterations"] == 250
    assert result["image_size"] == {"width": 800, "height": 600}
    assert result["working_size"] == {"width": 320, "height": 240}
    assert len(result["starts_final_loss"]) == 32
    assert result["joints"] == pytest.approx(JOINTS)
    truth = json.loads((DATA / "truth.json").read_text())
    assert np.linalg.norm(np.array(result["frames_px"]["tcp"]) - truth["point_px"]) < 5.0
    assert overlay.stat().st_size > 0 and history.stat().st_size > 0


@pytest.mark.slow
def test_pose_from_image_with_a_segmenter_and_zero_missing(tmp_path, capsys):
    readings = dict(JOINTS)
    del readings["left_finger_joint"]
    out = tmp_path / "result.json"
    argv = [*BASE, "--joints", joints_arg(readings), "--zero-missing", "--image", str(DATA / "image.png"),
            "--segmenter", "file", "--mask-pattern", str(DATA / "mask.png"), "--iterations", "6", "--starts", "2",
            "--working-max-side", "160", "--out", str(out)]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    assert result["joints"]["left_finger_joint"] == 0.0
    assert np.isfinite(np.array(result["T_cam_root"])).all()


def test_wrong_joint_names_and_counts(capsys):
    mask = ["--mask", str(DATA / "mask.png")]
    expect_error(capsys, [*BASE, *mask, "--joints", joints_arg({**JOINTS, "elbow": 1.0})],
                 "unknown joint name(s) 'elbow'", "expected readings for: joint1")
    partial = {name: JOINTS[name] for name in ("joint1", "joint2")}
    expect_error(capsys, [*BASE, *mask, "--joints", joints_arg(partial)],
                 "missing joint reading(s) for joint3, joint4, joint5, joint6")
    expect_error(capsys, [*BASE, *mask, "--joints", "joint1=0.1,joint2"], "--joints: expected NAME=VALUE")
    expect_error(capsys, [*BASE, *mask, "--joints", "joint1=0.1,joint1=0.2"], "given twice")
    expect_error(capsys, [*BASE, *mask, "--joints-file", str(DATA / "missing.json")], "joints file not found")


def test_unknown_links_and_unreadable_urdf(capsys, tmp_path):
    args = ["--joints-file", str(DATA / "joints.json"), "--mask", str(DATA / "mask.png")]
    expect_error(capsys, [*BASE[:-1], "shoulder", *args], "root: unknown link 'shoulder'", "links: base_link")
    expect_error(capsys, [*BASE, "--tip", "hand2", *args], "tip: unknown link 'hand2'")
    expect_error(capsys, [*BASE, "--exclude", "link1,nope", *args], "exclude: unknown link 'nope'")
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='x'><link name='a'></robot>")
    argv = [*BASE, *args]
    argv[argv.index("--urdf") + 1] = str(broken)
    expect_error(capsys, argv, "not valid XML")
    argv[argv.index("--urdf") + 1] = str(tmp_path / "missing.urdf")
    expect_error(capsys, argv, "robot description", "missing.urdf not found")


def test_bad_masks(capsys, tmp_path):
    empty, small = tmp_path / "empty.png", tmp_path / "small.png"
    write_mask(empty, np.zeros((600, 800), bool))
    write_mask(small, np.ones((240, 320), bool))
    args = ["--joints-file", str(DATA / "joints.json")]
    expect_error(capsys, [*BASE, *args, "--mask", str(empty)], "mask is empty")
    grey = tmp_path / "grey.png"
    cv2.imwrite(str(grey), np.full((600, 800, 3), 128, np.uint8))  # nothing the colour preset keeps
    expect_error(capsys, [*BASE, *args, "--image", str(grey), "--segmenter", "color"],
                 "grey.png: the color segmenter found no robot pixel", "--hsv-lower")
    expect_error(capsys, [*BASE, *args, "--mask", str(small)], "camera is 800x600 but image is 320x240")
    expect_error(capsys, [*BASE, *args, "--mask", str(tmp_path / "none.png")], "mask file not found")
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--iterations", "0"], "iterations")
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--polish-rounds", "-1"], "polish_rounds")
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--flip-candidates", "-1"], "flip_candidates")
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--cad-faces", "3"], "cad_faces")
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--polish-newton-steps", "-2"],
                 "polish_newton_steps")  # fmt: skip
    expect_error(capsys, [*BASE, *args, "--mask", str(DATA / "mask.png"), "--primitive-size", "area"],
                 "--primitive-size", "choose from 'bbox', 'volume'")  # fmt: skip


def test_primitive_choices_are_the_loaders():
    """The ``--primitive`` choices are spelled out in the CLI (it does not import the robot loader to build its
    parser); they must stay the loader's, in ``pose`` and in ``track pose``."""
    import argparse

    from pipeline.cli import build_parser
    from pipeline.robots.link_geometry import PRIMITIVE_CHOICES

    def sub(parser, name):
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return action.choices[name]

    root = build_parser()
    for parser in (sub(root, "pose"), sub(sub(root, "track"), "pose")):
        primitive = next(a for a in parser._actions if a.dest == "primitive")
        assert tuple(primitive.choices) == PRIMITIVE_CHOICES and primitive.default == "auto"


def test_fit_options_reach_the_config_and_default_to_the_librarys():
    """The fit options left out give ``PoseFitConfig``'s defaults (the CLI's own defaults do not drift from the
    library's); given, they reach the config."""
    from pipeline.cli import build_parser
    from pipeline.cli.pose import fit_config
    from pipeline.pose_estimation import PoseFitConfig

    required = BASE + ["--mask", "m.png", "--joints", "joint1=0"]
    config = fit_config(build_parser().parse_args(required))
    defaults = PoseFitConfig()
    for name in ("weight_hidden", "retry_weight_hidden", "weight_appearance", "retries", "starts", "seed",
                 "working_max_side", "flip_candidates", "fit_boundary_offset", "polish_boundary_offset",
                 "hull_points", "retry_outline_loss", "outline_polish", "boundary_refits"):
        assert getattr(config, name) == getattr(defaults, name), name
    config = fit_config(build_parser().parse_args(required + ["--weight-hidden", "0.5", "--retry-weight-hidden", "1"]))
    assert (config.weight_hidden, config.retry_weight_hidden) == (0.5, 1.0)
    assert fit_config(build_parser().parse_args(required + ["--hull-points", "48"])).hull_points == 48
    assert fit_config(build_parser().parse_args(required + ["--boundary-refits", "0"])).boundary_refits == 0
    for flag, expected in (("--outline-polish", True), ("--no-outline-polish", False)):
        assert fit_config(build_parser().parse_args(required + [flag])).outline_polish is expected
    for given, expected in (("0.2", 0.2), ("0", None)):  # 0: the hulls' own loss decides
        assert fit_config(build_parser().parse_args(required + ["--retry-outline-loss", given])).retry_outline_loss \
            == expected


def test_summary_line_says_when_another_pose_explains_the_mask():
    from pipeline.cli.pose import _summary_line

    T = np.eye(4)
    T[:3, 3] = (0.1, -0.2, 1.5)
    output = {"T_cam_root": T.tolist(), "depth_std_m": 0.012, "mask_dropped_fraction": 0.0, "loss": 0.0812,
              "iterations": 300, "seconds": 5.04, "ambiguous": False, "runner_up": None}  # fmt: skip
    line = _summary_line("out.json", output)
    assert line == ("out.json: T_cam_root t = (0.1000, -0.2000, 1.5000) m (depth +- 12 mm), loss 0.0812, "
                    "300 iterations, 5.0 s")
    runner = {"T_cam_root": T.tolist(), "loss": 0.09, "loss_ratio": 1.108, "rotation_deg": 176.4, "start": 3,
              "attempt": None}  # fmt: skip
    line = _summary_line("out.json", dict(output, ambiguous=True, runner_up=runner, depth_std_m=None,
                                          mask_dropped_fraction=0.031))
    assert line.startswith("out.json: T_cam_root t = (0.1000, -0.2000, 1.5000) m, loss 0.0812, 300 iterations, 5.0 s, "
                           "3.1% of the mask unexplained; ambiguous: a pose 176 degrees away explains the mask at "
                           "1.11x the loss"), line
    # a runner-up that is not within the flag's ratio is not mentioned
    assert "ambiguous" not in _summary_line("out.json", dict(output, runner_up=dict(runner, loss_ratio=2.5)))


def test_root_defaults_to_the_descriptions_top_link():
    """Without ``--root`` the robot is loaded from its description's top link (the toy arm's ``base_link``, the
    root every other test names), with the same links and joints."""
    from pipeline.cli import build_parser
    from pipeline.cli.pose import load_model

    argv = [a for a in BASE if a not in ("--root", "base_link")] + ["--mask", "m.png", "--joints", "joint1=0",
                                                                    "--primitive", "collision"]
    assert "--root" not in argv
    model = load_model(build_parser().parse_args(argv))
    named = load_model(build_parser().parse_args(argv + ["--root", "base_link"]))
    assert model.root == "base_link" and model.link_names == named.link_names
    assert model.joint_names == named.joint_names


def test_the_single_command_shows_the_loads_progress_and_a_batch_worker_does_not(monkeypatch):
    """``pose`` loads the robot with ``progress=True`` (a first CAD load takes a minute or two); a batch worker,
    whose parsed arguments carry a ``model_cache``, and ``--quiet`` (``track``'s) load without it."""
    import pipeline.robots.manipulator as manipulator
    from pipeline.cli import build_parser
    from pipeline.cli.pose import load_model

    seen = []
    real = manipulator.load_robot
    monkeypatch.setattr(manipulator, "load_robot", lambda *a, **k: seen.append(k) or real(*a, **k))
    argv = BASE + ["--mask", "m.png", "--joints", "joint1=0", "--primitive", "collision"]
    load_model(build_parser().parse_args(argv))
    assert seen[-1]["progress"] is True
    worker = build_parser().parse_args(argv)
    worker.model_cache = {}
    load_model(worker)
    assert seen[-1]["progress"] is False
    quiet = build_parser().parse_args(argv)
    quiet.quiet = True
    load_model(quiet)
    assert seen[-1]["progress"] is False


def test_cad_tolerance_reaches_the_loader(monkeypatch, capsys):
    """``--cad-tolerance-mm MM`` loads the robot with ``cad_tolerance_m = MM / 1000``; without it the loader's
    default is used, and 0 means none; a negative tolerance is one clear error line."""
    import pipeline.robots.manipulator as manipulator
    from pipeline.cli import build_parser
    from pipeline.cli.pose import load_model

    seen = []
    real = manipulator.load_robot
    monkeypatch.setattr(manipulator, "load_robot", lambda *a, **k: seen.append(k) or real(*a, **k))
    argv = BASE + ["--mask", "m.png", "--joints", "joint1=0", "--primitive", "collision"]
    load_model(build_parser().parse_args(argv))
    assert "cad_tolerance_m" not in seen[-1]  # the loader's default
    load_model(build_parser().parse_args(argv + ["--cad-tolerance-mm", "1.5"]))
    assert seen[-1]["cad_tolerance_m"] == pytest.approx(1.5e-3)
    load_model(build_parser().parse_args(argv + ["--cad-tolerance-mm", "0"]))
    assert seen[-1]["cad_tolerance_m"] is None
    expect_error(capsys, argv[:-2] + ["--primitive", "cad", "--cad-tolerance-mm", "-1"],
                 "cad_tolerance_m: expected a length > 0")
