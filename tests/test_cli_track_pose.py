"""``pipeline track pose``: a tiny synthetic sequence of the toy arm (masks from the painter's renderer, not the
fit's), the JSONL contract, joints from a CSV file, ``--static-camera``, and bad input (exit 2 with one line;
lines already written are kept)."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.camera import Camera
from pipeline.cli import main
from pipeline.evaluate import point_errors
from pipeline.io import write_image, write_json, write_mask
from pipeline.robots import load_robot
from pipeline.synth.pose import corrupt_mask, manipulator_sequence, painter_mask, render_robot_image
from pipeline.track import smoothed_pose

URDF = Path(__file__).resolve().parents[1] / "models" / "robots" / "toy_arm" / "toy_arm.urdf"
H, W = 120, 200
CAMERA = Camera(K=((170.0, 0.0, (W - 1) / 2), (0.0, 170.0, (H - 1) / 2), (0.0, 0.0, 1.0)), width=W, height=H)
# Small fits for fast tests; accuracy at the defaults is the benchmark's (benchmarks/bench_track.py).
QUICK = ["--iterations", "80", "--starts", "8", "--retries", "0", "--polish-rounds", "0", "--working-max-side", "200",
         "--warm-iterations", "20", "--warm-max-side", "200"]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """5 frames of the toy arm, joints moving, static camera: images, masks (painter's renderer), joints.csv and
    the camera; returns (folder, model, joint angles (5, J), T_cam_root (5, 4, 4))."""
    folder = tmp_path_factory.mktemp("pose_sequence")
    model = load_robot(URDF, "base_link")
    joints, poses = manipulator_sequence(model, CAMERA, np.random.default_rng(1), 5, period_frames=60.0,
                                         fill_range=(0.85, 0.95))
    for i, (q, T) in enumerate(zip(joints, poses)):
        image, _ = render_robot_image(model, q, T, CAMERA, np.random.default_rng(0))
        write_image(folder / "frames" / f"{i:05d}.png", image)
        write_mask(folder / "masks" / f"{i:05d}.png", painter_mask(model, q, T, CAMERA))
    write_joints_csv(folder / "joints.csv", model.joint_names, range(5), joints)
    write_json(folder / "camera.json", CAMERA.to_dict())
    return folder, model, joints, poses


def write_joints_csv(path, names, frames, joints, extra=""):
    rows = [",".join(["frame", "time_s", *names])]
    rows += [",".join([str(f), f"{f / 10:.3f}", *(f"{v:.9f}" for v in q)]) for f, q in zip(frames, joints)]
    path.write_text("\n".join(rows) + "\n" + extra)


def track(folder, *args, masks="masks", joints="joints.csv"):
    return main(["track", "pose", "--camera", str(folder / "camera.json"), "--robot", str(URDF), "--root",
                 "base_link", *QUICK, "--segmenter", "file", "--mask-pattern",
                 str(folder / masks / "{frame:05d}.png"), *(["--joints-csv", str(folder / joints)] if joints else []),
                 "--quiet", *args])


def read_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def error_line(capsys):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


def end_effector_mm(model, joints, T_est, T_true):
    tcp = model.frame_index("tcp")
    points = np.stack([model.link_frames_in_root(torch.from_numpy(q)[None])[0, tcp, :3, 3].numpy() for q in joints])
    return point_errors(np.asarray(T_est), np.asarray(T_true), points, CAMERA.K_array())["err_3d_mm"]


@pytest.mark.slow
def test_frames_with_a_joints_csv_give_one_line_per_frame_skipping_bad_frames(sequence, tmp_path, capsys):
    """Frame 2's image is corrupt (skipped, a line), frame 3 shows no robot (skipped), frame 1 has no CSV row
    (interpolated); the other frames' poses are near the truth, the overlay video has every frame."""
    folder, model, joints, poses = sequence
    run = tmp_path / "run"
    for i in range(5):
        (run / "frames").mkdir(parents=True, exist_ok=True)
        (run / "frames" / f"{i:05d}.png").write_bytes((folder / "frames" / f"{i:05d}.png").read_bytes())
        (run / "masks").mkdir(exist_ok=True)
        (run / "masks" / f"{i:05d}.png").write_bytes((folder / "masks" / f"{i:05d}.png").read_bytes())
    (run / "frames" / "00002.png").write_bytes(b"not a png")
    write_mask(run / "masks" / "00003.png", np.zeros((H, W), bool))
    write_joints_csv(run / "joints.csv", model.joint_names, [0, 2, 3, 4], joints[[0, 2, 3, 4]])
    (run / "camera.json").write_bytes((folder / "camera.json").read_bytes())
    out, overlay = tmp_path / "traj.jsonl", tmp_path / "overlay.mp4"
    assert track(run, "--frames", str(run / "frames" / "*.png"), "--interpolate-joints", "--out", str(out),
                 "--overlay-video", str(overlay), "--smooth-window", "8") == 0
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == [0, 1, 2, 3, 4]
    assert "unreadable" in lines[2]["skipped"] and "empty" in lines[3]["skipped"]
    tracked = [line for line in lines[:-1] if line["skipped"] is None]
    assert [line["frame"] for line in tracked] == [0, 1, 4]
    for line in lines[:-1]:
        assert set(line) == {"frame", "time_s", "T_cam_root", "loss", "depth_std_m", "iterations", "seconds",
                             "reinitialised", "skipped", "smooth_T_cam_root", "smooth_frames"}
        assert (line["depth_std_m"] is None) == (line["skipped"] is not None)  # the depth's error bar per frame
        assert line["depth_std_m"] is None or 0.0 < line["depth_std_m"] < 1.0
        assert (line["smooth_T_cam_root"] is None) == (line["skipped"] is not None)  # --smooth-window 8
    assert [line["smooth_frames"] for line in lines[:-3]] == [1, 2, 0]  # a skipped frame leaves the window
    window = tracked[3 - lines[4]["smooth_frames"]:]  # frame 4 may be fitted afresh after two skipped frames
    assert lines[4]["smooth_frames"] == 3 or lines[4]["reinitialised"]
    np.testing.assert_allclose(lines[4]["smooth_T_cam_root"], smoothed_pose(
        [(line["frame"], np.array(line["T_cam_root"])) for line in window]), atol=1e-12)
    errors = end_effector_mm(model, joints[[0, 1, 4]], [line["T_cam_root"] for line in tracked], poses[[0, 1, 4]])
    assert errors.max() < 25.0, errors
    assert tracked[1]["iterations"] < tracked[0]["iterations"]  # warm-started
    summary = lines[-1]
    assert summary["summary"] is True and summary["frames"] == 5 and summary["skipped"] == 2
    assert summary["fps"] > 0 and "T_cam_root" not in summary
    assert 0 <= summary["drift_reinitialisations"] <= summary["reinitialisations"]
    import cv2

    capture = cv2.VideoCapture(str(overlay))
    count = 0
    while capture.read()[0]:
        count += 1
    assert count == 5
    assert "5 frames (2 skipped" in capsys.readouterr().out


def tracker_config(folder, monkeypatch, *args):
    """The ``PoseTrackConfig`` that ``track pose ... ARGS`` builds (the tracker is stopped before any fit)."""
    import pipeline.track

    seen = []

    class Stop(Exception):
        pass

    def capture(self, model, camera, config):
        seen.append(config)
        raise Stop

    monkeypatch.setattr(pipeline.track.PoseTracker, "__init__", capture)
    with pytest.raises(Stop):
        track(folder, "--frames", str(folder / "frames" / "*.png"), "--out", "unused.jsonl", *args)
    return seen[-1]


def test_weight_hidden_reaches_the_full_and_the_warm_fits(sequence, monkeypatch):
    """``--weight-hidden`` (a mask with holes in every frame) sets the first frame's fit and the warm fits."""
    for args, weight in (((), 1.0), (("--weight-hidden", "0.25"), 0.25)):
        config = tracker_config(sequence[0], monkeypatch, *args)
        assert config.full_fit.weight_hidden == weight and config.warm_fit.weight_hidden == weight


def test_smooth_window_reaches_the_tracker(sequence, monkeypatch, capsys):
    """``--smooth-window N`` sets ``PoseTrackConfig.smooth_window`` (default ``SMOOTH_WINDOW``; 1: none); below 1 it
    stops the run with one line naming the option."""
    from pipeline.cli.track import SMOOTH_WINDOW

    folder = sequence[0]
    assert SMOOTH_WINDOW == 1  # off by default
    for args, window in (((), None), (("--smooth-window", "1"), None), (("--smooth-window", "3"), 3)):
        assert tracker_config(folder, monkeypatch, *args).smooth_window == window
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--out", "unused.jsonl",
                 "--smooth-window", "0") == 2
    assert "--smooth-window: expected an int >= 1, got 0" in capsys.readouterr().err


@pytest.mark.slow
def test_static_camera_joint_estimate_beats_the_median_frame_and_ignores_a_wrong_mask(sequence, tmp_path):
    """Noisy masks (a wobbly boundary, a 1 px dilation or erosion per frame after the first) and one mask that is
    wrong (shifted by 12 px): the static-camera estimate's end-effector error is below the median of the frames'
    own, and that frame is the one trimmed. The running estimate (``--static-running-first 2``: refined after 2
    and 4 frames) is in every line, from the frames up to it, and nearer than the median frame's own from 4."""
    folder, model, joints, poses = sequence
    rng = np.random.default_rng(7)
    import cv2

    for i, (q, T) in enumerate(zip(joints, poses)):
        mask = painter_mask(model, q, T, CAMERA)
        if i > 0:  # the first frame's full fit is the tracker's business; these tests are about the others
            mask = corrupt_mask(mask, rng, boundary_noise_px=0.7)
            mask = (cv2.dilate if i % 2 else cv2.erode)(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        if i == 2:
            mask = np.roll(mask, 12, axis=1)
        write_mask(tmp_path / "masks" / f"{i:05d}.png", mask)
    for name in ("camera.json", "joints.csv"):
        (tmp_path / name).write_bytes((folder / name).read_bytes())
    out = tmp_path / "traj.jsonl"
    assert track(tmp_path, "--frames", str(folder / "frames" / "*.png"), "--static-camera", "--static-trim", "0.2",
                 "--static-running-first", "2", "--out", str(out)) == 0
    lines = read_lines(out)
    summary = lines[-1]
    per_frame = end_effector_mm(model, joints, [line["T_cam_root"] for line in lines[:-1]], poses)
    joint = end_effector_mm(model, joints, [summary["T_cam_root"]] * 5, poses)
    assert np.median(joint) < np.median(per_frame), (joint, per_frame)
    assert [line["static_frames"] for line in lines[:-1]] == [0, 2, 2, 4, 4]
    assert lines[0]["static_T_cam_root"] is None and lines[0]["static_seconds"] == 0.0
    refined = [line["static_seconds"] > 0.0 for line in lines[:-1]]
    assert refined == [False, True, False, True, False]
    assert lines[2]["static_T_cam_root"] == lines[1]["static_T_cam_root"] != lines[3]["static_T_cam_root"]
    assert summary["static_camera"]["running_seconds"] == pytest.approx(sum(line["static_seconds"] for line in lines[:-1]))
    running = end_effector_mm(model, joints, [lines[4]["static_T_cam_root"]] * 5, poses)
    assert np.median(running) < np.median(per_frame), (running, per_frame)
    assert summary["static_camera"]["trimmed"] == [2] and summary["static_camera"]["frames"] == [0, 1, 2, 3, 4]
    static = summary["static_camera"]  # primitives: no boundary offsets; the polish's record
    assert static["boundary_offsets_px"] == [0.0] * 5 and static["loss"] <= static["loss_before_polish"]
    assert 0 <= static["polish_steps"] <= 10 and static["outline"] is False  # the toy arm's primitives: no outline


def test_joints_csv_errors_name_the_row_and_column(sequence, tmp_path, capsys):
    folder, model, joints, _ = sequence
    (tmp_path / "camera.json").write_bytes((folder / "camera.json").read_bytes())
    frames = str(folder / "frames" / "*.png")
    names = list(model.joint_names)
    cases = {
        "missing.csv": (names[1:], "no column for joint(s) joint1"),
        "unknown.csv": ([*names, "gripper_cmd"], "column 'gripper_cmd' is no joint"),
    }
    for file, (columns, message) in cases.items():
        write_joints_csv(tmp_path / file, columns, range(5), np.zeros((5, len(columns))))
        assert track(tmp_path, "--frames", frames, joints=file, masks=folder / "masks") == 2
        assert message in error_line(capsys)
    write_joints_csv(tmp_path / "text.csv", names, range(5), joints)
    text = (tmp_path / "text.csv").read_text().splitlines()
    cells = text[3].split(",")
    cells[4] = "abc"  # line 4 (frame 2), the column of joint3
    text[3] = ",".join(cells)
    (tmp_path / "text.csv").write_text("\n".join(text) + "\n")
    assert track(tmp_path, "--frames", frames, joints="text.csv", masks=folder / "masks") == 2
    assert "text.csv line 4, column joint3: expected a finite number, got 'abc'" in error_line(capsys)
    write_joints_csv(tmp_path / "one.csv", names, [0], joints[:1])
    assert track(tmp_path, "--frames", frames, "--interpolate-joints", joints="one.csv", masks=folder / "masks") == 2
    assert "at least 2 row(s)" in error_line(capsys)
    assert track(tmp_path, "--frames", frames, "--interpolate-joints", "--joints", "joint1=0", joints=None,
                 masks=folder / "masks") == 2
    assert "--interpolate-joints goes with --joints-csv" in error_line(capsys)
    assert track(tmp_path, "--frames", frames, "--joints", "joint1=0,elbow=1", joints=None,
                 masks=folder / "masks") == 2  # constant readings for every frame, checked as pose checks them
    assert "unknown joint name(s) 'elbow'" in error_line(capsys)


def test_bad_video_and_missing_masks_exit_2_with_one_line(sequence, tmp_path, capsys):
    folder, _, _, _ = sequence
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    assert track(folder, "--video", str(empty)) == 2
    assert "--video" in error_line(capsys)
    assert track(folder, "--frames", str(tmp_path / "none" / "*.png")) == 2
    assert "no file matches" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), masks=tmp_path / "nomasks") == 2
    assert "00000.png" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--static-camera",
                 "--static-polish-steps", "-1") == 2
    assert "--static-polish-steps" in error_line(capsys)
    for bad in ("abc", "0.5"):
        assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--drift-ratio", bad) == 2
        err = error_line(capsys)
        assert "drift" in err and "> 1" in err and bad in err, err
    for bad in ("1", "0.5", "inf"):
        assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-calm", bad) == 2
        assert f"--warm-calm: expected a finite number > 1 (times the running loss), got {float(bad)}" in error_line(
            capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-outline-loss", "0.1") == 2
    assert ("--warm-outline-loss is a setting of --warm-outline-polish auto or --warm-boundary-offset auto, but they "
            "are never and never") in error_line(capsys)


@pytest.mark.slow
def test_a_frame_without_a_csv_row_stops_the_run_keeping_the_lines_written(sequence, tmp_path, capsys):
    folder, model, joints, _ = sequence
    (tmp_path / "camera.json").write_bytes((folder / "camera.json").read_bytes())
    write_joints_csv(tmp_path / "joints.csv", model.joint_names, [0, 2, 3], joints[[0, 2, 3]])
    out = tmp_path / "traj.jsonl"
    assert track(tmp_path, "--frames", str(folder / "frames" / "*.png"), "--out", str(out),
                 masks=folder / "masks") == 2
    assert "no row for frame 1" in error_line(capsys)
    assert [line["frame"] for line in read_lines(out)] == [0]


def test_warm_fit_options_default_to_the_librarys():
    """``--warm-iterations``, ``--warm-max-side``, ``--warm-newton-steps``, ``--warm-target`` and
    ``--weight-appearance`` (which the warm fits follow) left out give ``WARM_POSE_FIT``'s values (the CLI's defaults do not drift from the
    library's); so do the ``--static-*`` options ``StaticCameraConfig``'s."""
    import argparse

    from pipeline.cli import build_parser
    from pipeline.pose_estimation import StaticCameraConfig
    from pipeline.track import WARM_POSE_FIT, PoseTrackConfig

    def sub(parser, name):
        action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        return action.choices[name]

    parser = sub(sub(build_parser(), "track"), "pose")
    defaults = {a.dest: a.default for a in parser._actions}
    assert defaults["warm_iterations"] == WARM_POSE_FIT.iterations
    assert defaults["warm_max_side"] == WARM_POSE_FIT.working_max_side
    assert defaults["warm_newton_steps"] == WARM_POSE_FIT.polish_newton_steps
    assert defaults["weight_appearance"] == WARM_POSE_FIT.weight_appearance
    assert (defaults["warm_target"] == "coverage") == WARM_POSE_FIT.coverage_target \
        == StaticCameraConfig().coverage_target
    assert defaults["reinit_ratio"] == PoseTrackConfig().reinit_ratio
    assert defaults["reinit_limit"] == PoseTrackConfig().reinit_limit
    assert float(defaults["drift_ratio"]) == PoseTrackConfig().drift_ratio
    static = StaticCameraConfig()  # and the --static-camera refinement's
    assert (defaults["static_iterations"], defaults["static_frames"], defaults["static_trim"],
            defaults["static_polish_steps"]) == (static.iterations, static.max_frames, static.trim_fraction,
                                                 static.polish_steps)
    assert defaults["static_outline_polish"] == static.outline_polish
    assert defaults["static_running_first"] == PoseTrackConfig().running_static_first
    assert defaults["carry_moments"] is PoseTrackConfig().carry_moments is True  # since session 71
    assert defaults["warm_outline_polish"] == "never" and WARM_POSE_FIT.outline_polish is None  # warm fits: no retry
    assert WARM_POSE_FIT.outline_polish_loss is None  # and no polish asked of the meshes unless "auto"
    assert defaults["warm_boundary_offset"] == "never" and WARM_POSE_FIT.offset_polish_loss is None
    assert WARM_POSE_FIT.polish_boundary_offset is None  # the geometry's: fitted with CAD, not with hulls
    assert defaults["warm_outline_loss"] is None  # with auto: the single fit's retry_outline_loss (run_pose)


@pytest.mark.parametrize("target", ["coverage", "threshold"])
def test_warm_target_reaches_the_warm_fits_and_the_static_camera(sequence, tmp_path, monkeypatch, target):
    """``--warm-target`` sets ``coverage_target`` of the warm fits' config and of the ``--static-camera``
    refinement's, ``--warm-outline-polish`` (bare: always) and ``--[no-]static-outline-polish`` their ``outline_polish``,
    ``--warm-outline-polish auto --warm-outline-loss L`` the warm fits' ``outline_polish_loss``,
    ``--warm-boundary-offset always`` their ``polish_boundary_offset`` and ``auto`` (the same bar L) their
    ``offset_polish_loss``, ``--drift-ratio none`` the tracker's ``drift_ratio``, ``--no-carry-moments`` its
    ``carry_moments`` (all recorded; a short run: only the wiring is under test)."""
    import pipeline.track

    folder = sequence[0]
    seen = {}

    class Recorder(pipeline.track.PoseTracker):
        def __init__(self, model, camera, config):
            seen["warm"] = config.warm_fit.coverage_target
            seen["warm outline"] = (config.warm_fit.outline_polish, config.warm_fit.outline_polish_loss)
            seen["warm offset"] = (config.warm_fit.polish_boundary_offset, config.warm_fit.offset_polish_loss)
            seen["drift"] = config.drift_ratio
            seen["carry"] = config.carry_moments
            super().__init__(model, camera, config)

    refine_static_camera = pipeline.track.refine_static_camera

    def refine(masks, joints, model, camera, starts, config):
        seen["static"] = config.coverage_target
        seen["static outline"] = config.outline_polish
        seen.setdefault("refinements", []).append((len(masks), config.candidates, config.iterations))
        return refine_static_camera(masks, joints, model, camera, starts, config)

    monkeypatch.setattr(pipeline.track, "PoseTracker", Recorder)
    monkeypatch.setattr(pipeline.track, "refine_static_camera", refine)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-target", target, "--static-camera",
                 "--static-iterations", "5", "--static-polish-steps", "0", "--out", str(tmp_path / "t.jsonl"),
                 *(["--warm-outline-polish", "--static-outline-polish", "--drift-ratio", "none", "--no-static-running",
                    "--warm-boundary-offset", "always", "--no-carry-moments"]
                   if target == "threshold" else ["--warm-outline-polish", "auto", "--warm-outline-loss", "0.5",
                                                  "--warm-boundary-offset", "auto",
                                                  "--no-static-outline-polish", "--static-running-first", "3"])) == 0
    assert seen == {"warm": target == "coverage", "static": target == "coverage",
                    "warm outline": (True, None) if target == "threshold" else (None, 0.5),
                    "warm offset": (True, None) if target == "threshold" else (None, 0.5),
                    "drift": None if target == "threshold" else 3.0,
                    "carry": target == "coverage",  # Adam's state carried by default since session 71
                    "static outline": target == "threshold",
                    # the running estimate after 3 frames (3 starts scored, at most --static-iterations), then all 5
                    "refinements": [(5, 8, 5)] if target == "threshold" else [(3, 3, 5), (5, 8, 5)]}
    lines = read_lines(tmp_path / "t.jsonl")[:-1]
    assert all(("static_T_cam_root" in line) == (target == "coverage") for line in lines)


def test_static_polish_takes_a_near_miss_to_the_truth(sequence):
    """``refine_static_camera``'s Levenberg-Marquardt polish alone (the Adam steps held still by a zero-ish rate),
    clean painter masks, from the true pose 3 % too far and turned 1.5 degrees: the polish ends far nearer the
    truth than its start, at a lower trimmed loss; without it the start comes back."""
    from pipeline.geometry import rotvec_to_rotmat
    from pipeline.pose_estimation import StaticCameraConfig, refine_static_camera

    _, model, joints, poses = sequence
    masks = [painter_mask(model, q, T, CAMERA) for q, T in zip(joints, poses)]
    start = poses[0].copy()
    start[:3, :3] = rotvec_to_rotmat(torch.tensor([[0.0, np.radians(1.5), 0.0]]))[0].numpy() @ start[:3, :3]
    start[:3, 3] *= 1.03
    angles = [torch.from_numpy(q) for q in joints]
    still = {"iterations": 1, "lr_pose": 1e-12, "trim_fraction": 0.0}
    before = refine_static_camera(masks, angles, model, CAMERA, [start], StaticCameraConfig(polish_steps=0, **still))
    after = refine_static_camera(masks, angles, model, CAMERA, [start], StaticCameraConfig(polish_steps=10, **still))
    err_before = np.median(end_effector_mm(model, joints, [before.T_cam_root] * 5, poses))
    err_after = np.median(end_effector_mm(model, joints, [after.T_cam_root] * 5, poses))
    assert err_before > 40.0 and before.polish_steps == 0
    assert err_after < err_before / 4, (err_before, err_after)
    assert after.loss < after.loss_before_polish == pytest.approx(before.loss) and after.polish_steps >= 1


def test_static_polish_fits_each_frames_outline_bias_with_cad_links():
    """With CAD links the polish also fits each frame's boundary offset (as a single-frame CAD fit does): masks of
    the toy arm's meshes eroded (even frames) or dilated (odd frames) by one pixel, the pose started at the truth:
    the offsets come out with each frame's sign (negative: the true outline lies outside an eroded mask), and the
    pose stays nearer the truth than when the offsets are not fitted (the biased masks then pull it: about 3
    against 50 mm)."""
    import cv2

    from pipeline.pose_estimation import StaticCameraConfig, refine_static_camera

    model = load_robot(URDF.parents[1] / "toy_arm_mesh" / "toy_arm_mesh.urdf", "base_link", primitive="cad")
    joints, poses = manipulator_sequence(model, CAMERA, np.random.default_rng(3), 6, period_frames=20.0,
                                         fill_range=(0.85, 0.95))
    masks = [(cv2.dilate if i % 2 else cv2.erode)(painter_mask(model, q, T, CAMERA).astype(np.uint8),
                                                  np.ones((3, 3), np.uint8)) > 0
             for i, (q, T) in enumerate(zip(joints, poses))]
    angles = [torch.from_numpy(q) for q in joints]
    still = {"iterations": 1, "lr_pose": 1e-12, "trim_fraction": 0.0, "polish_steps": 10}
    fitted = refine_static_camera(masks, angles, model, CAMERA, [poses[0]], StaticCameraConfig(**still))
    plain = refine_static_camera(masks, angles, model, CAMERA, [poses[0]],
                                 StaticCameraConfig(polish_boundary_offset=False, **still))
    assert np.array_equal(np.sign(fitted.boundary_offsets_px), [-1, 1, -1, 1, -1, 1]), fitted.boundary_offsets_px
    assert not plain.boundary_offsets_px.any()
    tcp = model.frame_index("tcp")
    points = np.stack([model.link_frames_in_root(torch.from_numpy(q)[None])[0, tcp, :3, 3].numpy() for q in joints])

    def error_mm(T):
        return np.median(point_errors(np.repeat(T[None], 6, 0), poses, points, CAMERA.K_array())["err_3d_mm"])

    assert error_mm(fitted.T_cam_root) < error_mm(plain.T_cam_root)
    # a working side below the masks' (two mask pixels a working pixel): the level sets are cut from the
    # full-resolution masks and compared by their coverage, as the refinement's own coverage target (measured
    # 2.8 mm; 22.4 when they were cut from the thresholded working masks: the polish then compared its steps
    # against another loss than its start's)
    coarse = refine_static_camera(masks, angles, model, CAMERA, [poses[0]],
                                  StaticCameraConfig(working_max_side=100, **still))
    assert error_mm(coarse.T_cam_root) < 8.0


def test_static_polish_draws_the_visual_meshes_where_links_are_hulls():
    """``StaticCameraConfig.outline_polish``: a model drawn with link hulls keeps its visual meshes (``outline``;
    UR5's, from example-robot-data, a test extra); the polish alone (the Adam steps held still), started at the
    truth on the meshes' clean masks, drifts off it drawn with the hulls (a hull is wider than its link: 7.2 mm
    measured) and stays on it drawn with the meshes (0.35 mm); on masks dilated by one pixel it fits each frame's
    boundary offset (about 3 reference pixels at 200 px wide). Without an outline the option changes nothing."""
    import sysconfig

    import cv2

    from pipeline.pose_estimation import StaticCameraConfig, refine_static_camera

    robots = Path(sysconfig.get_paths()["purelib"]) / "cmeel.prefix" / "share" / "example-robot-data" / "robots"
    urdf = robots / "ur_description" / "urdf" / "ur5_robot.urdf"
    if not urdf.is_file():
        pytest.skip(f"example-robot-data is not installed ({urdf} missing): pip install example-robot-data")
    hulls = load_robot(urdf, "base_link")
    joints, poses = manipulator_sequence(hulls.outline, CAMERA, np.random.default_rng(4), 5, period_frames=20.0,
                                         fill_range=(0.85, 0.95))
    clean = [painter_mask(hulls.outline, q, T, CAMERA) for q, T in zip(joints, poses)]
    dilated = [cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0 for m in clean]
    angles = [torch.from_numpy(q) for q in joints]
    tool = hulls.frame_index("tool0")
    points = np.stack([hulls.link_frames_in_root(torch.from_numpy(q)[None])[0, tool, :3, 3].numpy() for q in joints])

    def error_mm(result):
        T = np.repeat(result.T_cam_root[None], 5, 0)
        return np.median(point_errors(T, poses, points, CAMERA.K_array())["err_3d_mm"])

    assert StaticCameraConfig().outline_polish is True  # the default (docs/tracking.md: nearer on 10 of 15 videos)
    still = {"iterations": 1, "lr_pose": 1e-12, "trim_fraction": 0.0, "polish_steps": 10}
    hull_fit, outline_fit = (refine_static_camera(clean, angles, hulls, CAMERA, [poses[0]], StaticCameraConfig(
        outline_polish=polish, **still)) for polish in (False, True))
    assert not hull_fit.outline and outline_fit.outline
    assert error_mm(hull_fit) > 3.0 and error_mm(outline_fit) < 1.0, (error_mm(hull_fit), error_mm(outline_fit))
    assert outline_fit.loss < outline_fit.loss_before_polish  # the outline's loss; before: the hulls'
    biased = refine_static_camera(dilated, angles, hulls, CAMERA, [poses[0]],
                                  StaticCameraConfig(outline_polish=True, **still))
    np.testing.assert_allclose(biased.boundary_offsets_px, 3.1, atol=0.6)
    assert error_mm(biased) < 8.0  # measured 4.2 mm (hulls: 15.5, the meshes without the offsets: 36.5)
    toy = load_robot(URDF, "base_link")  # its own primitives: no outline
    toy_joints, toy_poses = manipulator_sequence(toy, CAMERA, np.random.default_rng(1), 3, period_frames=20.0,
                                                 fill_range=(0.85, 0.95))
    toy_masks = [painter_mask(toy, q, T, CAMERA) for q, T in zip(toy_joints, toy_poses)]
    a, b = (refine_static_camera(toy_masks, [torch.from_numpy(q) for q in toy_joints], toy, CAMERA, [toy_poses[0]],
                                 StaticCameraConfig(outline_polish=polish, iterations=3, polish_steps=2))
            for polish in (False, True))
    assert not b.outline and np.array_equal(a.T_cam_root, b.T_cam_root) and a.loss == b.loss
