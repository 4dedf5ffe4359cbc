"""``pipeline track shape``: a tiny synthetic sequence from image files and from a video, the JSONL contract, and
bad input (exit 2 with one line; lines already written are kept)."""

import json

import cv2
import numpy as np
import pytest

from pipeline.camera import Camera
from pipeline.cli import main
from pipeline.evaluate import centerline_errors
from pipeline.io import write_image, write_json, write_mask
from pipeline.shapes.polyline import bezier_centerline
from pipeline.synth.soft_arm import moving_bezier_arm, render_tube_image

H, W = 180, 320
K = np.array([[175.0, 0.0, (W - 1) / 2], [0.0, 175.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
ARM = ["--length", "0.2", "--base-radius", "0.014", "--tip-radius", "0.006"]
QUICK = ["--iterations", "60", "--starts", "2", "--warm-iterations", "10", "--warm-prefit-iterations", "100"]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """4 frames of a moving arm: images, masks and the camera file; returns (folder, true centrelines)."""
    folder = tmp_path_factory.mktemp("sequence")
    control = moving_bezier_arm(np.random.default_rng(3), K, (H, W), 4, period_frames=40.0)
    truths = [bezier_centerline(c, 201) for c in control]
    for i, truth in enumerate(truths):
        image, mask = render_tube_image(truth, np.linspace(0.014, 0.006, 201), K, (H, W), np.random.default_rng(0))
        write_image(folder / "frames" / f"{i:05d}.png", image)
        write_mask(folder / "masks" / f"{i:05d}.png", mask)
    write_json(folder / "camera.json", Camera(K=K.tolist(), width=W, height=H).to_dict())
    return folder, truths


def track(folder, *args):
    return main(["track", "shape", "--camera", str(folder / "camera.json"), *ARM, *QUICK, "--segmenter", "file",
                 "--mask-pattern", str(folder / "masks" / "{frame:05d}.png"), *args])


def read_lines(path):
    return [json.loads(line) for line in path.read_text().splitlines()]


def frames_with_an_unreadable_one(folder, tmp_path, *, count, unreadable):
    """The sequence's first ``count`` images copied to ``tmp_path/frames``, image ``unreadable`` replaced by junk."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(count):
        (frames / f"{i:05d}.png").write_bytes((folder / "frames" / f"{i:05d}.png").read_bytes())
    (frames / f"{unreadable:05d}.png").write_bytes(b"not a png")
    return frames


def video_frame_count(path):
    capture = cv2.VideoCapture(str(path))
    count = 0
    while capture.read()[0]:
        count += 1
    return count


def error_line(capsys):
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1, err
    return err


@pytest.mark.slow
def test_frames_glob_writes_one_line_per_frame_and_a_summary(sequence, tmp_path, capsys):
    folder, truths = sequence
    out = tmp_path / "traj.jsonl"
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--out", str(out)) == 0
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == [0, 1, 2, 3]
    for line in lines[:-1]:
        assert line["skipped"] is None and line["time_s"] is None and isinstance(line["reinitialised"], bool)
        assert len(line["centerline_cam_m"]) == 101 and 3 <= len(line["control_points_cam_m"]) <= 6  # order 2-5
        assert line["loss"] > 0 and line["seconds"] > 0 and line["iterations"] > 0
        error = centerline_errors(np.array(line["centerline_cam_m"]), truths[line["frame"]], K)["mean_2d_px"]
        assert error < 3.0
    summary = lines[-1]
    assert summary["summary"] is True and summary["frames"] == 4 and summary["skipped"] == 0
    assert summary["fps"] > 0 and {"decode_seconds", "segment_seconds", "fit_seconds", "write_seconds"} <= set(summary)
    assert "4 frames" in capsys.readouterr().out
    # By default the masks are taken as exact: no rim read (--rim-offset-px image reads it from the frames)
    assert summary["rim_offset_px"] == 0.0 and "rim_offset_readings" not in summary
    assert all(line["rim_offset_px"] == 0.0 for line in lines[:-1])
    assert 0 <= summary["drift_reinitialisations"] <= summary["reinitialisations"]


@pytest.mark.slow
def test_video_with_start_and_step_and_an_overlay_video(sequence, tmp_path):
    folder, _ = sequence
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 5.0, (W, H))
    for i in range(4):
        writer.write(cv2.imread(str(folder / "frames" / f"{i:05d}.png")))
    writer.release()
    out, overlay = tmp_path / "traj.jsonl", tmp_path / "overlay.mp4"
    assert track(folder, "--video", str(video), "--start", "1", "--step", "2", "--out", str(out),
                 "--overlay-video", str(overlay)) == 0
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == [1, 3]
    assert [line["time_s"] for line in lines[:-1]] == pytest.approx([0.2, 0.6])
    assert video_frame_count(overlay) == 2


@pytest.mark.slow
def test_a_clutter_blob_of_the_arms_colour_larger_than_the_arm_is_not_tracked(sequence, tmp_path):
    """From frame 1 on, a blob of the arm's colour twice its area (the colour segmenter marks it as the arm): the
    command's segmenter keeps every component and the tracker follows the arm's; with the largest component alone,
    as ``pipeline shape`` first segments, every frame from 1 would be the blob's."""
    from pipeline.synth.soft_arm import DEFAULT_ARM_COLOR_BGR

    folder, truths = sequence
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(3):
        image = cv2.imread(str(folder / "frames" / f"{i:05d}.png"))
        if i >= 1:  # lower-left, clear of the arm in these frames
            cv2.ellipse(image, (60, 140), (48, 24), 0, 0, 360, DEFAULT_ARM_COLOR_BGR, -1)
        write_image(frames / f"{i:05d}.png", image)
    arm = cv2.imread(str(folder / "masks" / "00001.png"), cv2.IMREAD_GRAYSCALE) > 0
    assert np.pi * 48 * 24 > 2 * arm.sum() and not arm[116:165, 12:109].any()
    out = tmp_path / "traj.jsonl"
    assert main(["track", "shape", "--camera", str(folder / "camera.json"), *ARM, *QUICK, "--segmenter", "color",
                 "--frames", str(frames / "*.png"), "--out", str(out), "--rim-offset-px", "image"]) == 0
    lines, summary = read_lines(out)[:-1], read_lines(out)[-1]
    # --rim-offset-px image: the rim read from each frame (arms this narrow read 0), each fit at the median so far
    readings = summary["rim_offset_readings"]
    assert len(readings) == 3 and summary["rim_offset_px"] == pytest.approx(np.median(readings))
    assert [line["rim_offset_px"] for line in lines] == pytest.approx([np.median(readings[:i + 1]) for i in range(3)])
    errors = [centerline_errors(np.array(line["centerline_cam_m"]), truths[line["frame"]], K)["mean_2d_px"]
              for line in lines]
    # (the colour segmenter's anti-aliased rim costs these small quick fits 3-4 px already; the blob is 80+ px off)
    assert all(line["skipped"] is None for line in lines) and max(errors) < 6.0, errors


@pytest.mark.slow
def test_unreadable_frame_is_skipped_and_tracking_goes_on(sequence, tmp_path):
    folder, _ = sequence
    frames = frames_with_an_unreadable_one(folder, tmp_path, count=3, unreadable=1)
    out = tmp_path / "traj.jsonl"
    assert track(folder, "--frames", str(frames / "*.png"), "--out", str(out)) == 0
    lines = read_lines(out)
    assert "unreadable" in lines[1]["skipped"] and lines[1]["centerline_cam_m"] is None
    assert lines[2]["skipped"] is None and lines[-1]["skipped"] == 1


@pytest.mark.slow
def test_batch_frames_keep_the_lines_in_order_around_an_unreadable_frame(sequence, tmp_path):
    """``--batch-frames 3``: the first frame alone, then warm frames in batches; an unreadable frame first sends the
    frames before it off as a batch (1 and 2 together) and is written after them, the others fit (the JSONL as one
    frame at a time) and the overlay has every frame."""
    folder, truths = sequence
    frames = frames_with_an_unreadable_one(folder, tmp_path, count=4, unreadable=3)
    out, overlay = tmp_path / "traj.jsonl", tmp_path / "overlay.mp4"
    assert track(folder, "--frames", str(frames / "*.png"), "--batch-frames", "3", "--out", str(out),
                 "--overlay-video", str(overlay)) == 0
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == [0, 1, 2, 3]
    assert "unreadable" in lines[3]["skipped"] and lines[-1]["skipped"] == 1 and lines[-1]["frames"] == 4
    for line in lines[:3]:
        error = centerline_errors(np.array(line["centerline_cam_m"]), truths[line["frame"]], K)["mean_2d_px"]
        assert line["skipped"] is None and error < 3.0
    assert video_frame_count(overlay) == 4


@pytest.mark.slow
def test_rim_offset_auto_is_searched_over_the_first_frames(sequence, tmp_path, capsys):
    """``--rim-offset-px auto --rim-search-frames 2`` on masks 2 px too wide: the first two frames are written
    once the offset is found, refitted at it like every later frame (``rim_offset_px`` on each line), and the
    summary holds it with the frames' mean loss at each offset tried."""
    folder, _ = sequence
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    for i in range(3):
        mask = cv2.imread(str(folder / "masks" / f"{i:05d}.png"), cv2.IMREAD_GRAYSCALE) > 0
        write_mask(tmp_path / "wide" / f"{i:05d}.png", cv2.dilate(mask.astype(np.uint8), disk) > 0)
    out = tmp_path / "traj.jsonl"
    assert main(["track", "shape", "--camera", str(folder / "camera.json"), *ARM, *QUICK, "--segmenter", "file",
                 "--mask-pattern", str(tmp_path / "wide" / "{frame:05d}.png"), "--frames",
                 str(folder / "frames" / "*.png"), "--stop", "3", "--rim-offset-px", "auto",
                 "--rim-search-frames", "2", "--out", str(out)]) == 0
    lines = read_lines(out)
    held = lines[-1]["rim_offset_px"]
    assert [line["frame"] for line in lines[:-1]] == [0, 1, 2] and held > 0
    assert [line["rim_offset_px"] for line in lines[:-1]] == [held] * 3
    assert len(lines[-1]["rim_offset_losses"]) == 5 and f"rim offset {held:+g} px" in capsys.readouterr().out


def test_warm_prefit_options_reach_the_warm_fit(sequence, monkeypatch, capsys):
    """``--warm-prefit-solver``, ``--warm-prefit-iterations`` (6 Levenberg-Marquardt or 100 Adam steps unless
    given) and ``--no-warm-keep-start`` set the tracker's warm fit (the tracker stopped before any frame); the
    fits' working side and the drift ratio default to the library's; ``--drift-ratio none|R`` reaches the
    tracker. ``--model auto`` (a model chosen image by image) is not a choice of the tracker."""
    import pipeline.track
    from pipeline.shape_estimation import ShapeFitConfig

    class Built(Exception):
        pass

    def tracker(robot, camera, config, **kwargs):
        raise Built(config)

    monkeypatch.setattr(pipeline.track, "ShapeTracker", tracker)
    folder, _ = sequence
    base = ["track", "shape", "--camera", str(folder / "camera.json"), *ARM,
            "--frames", str(folder / "frames" / "*.png")]
    adam_7_unkept = ("--warm-prefit-solver", "adam", "--warm-prefit-iterations", "7", "--no-warm-keep-start")
    expected = {(): ("lm", 6, True), ("--warm-prefit-solver", "adam"): ("adam", 100, True),
                adam_7_unkept: ("adam", 7, False)}
    for options, (solver, steps, keep) in expected.items():
        with pytest.raises(Built) as built:
            main([*base, *options])
        config = built.value.args[0]
        warm = config.warm_fit
        assert (warm.prefit_solver, warm.prefit_iterations, warm.warm_keep_start) == (solver, steps, keep)
        # The full and warm fits' working side defaults to the library's (the CLI's own default does not drift).
        assert config.full_fit.working_max_side == warm.working_max_side == ShapeFitConfig().working_max_side
        assert config.drift_ratio == pipeline.track.ShapeTrackConfig().drift_ratio
    for text, ratio in (("none", None), ("3", 3.0)):
        with pytest.raises(Built) as built:
            main([*base, "--drift-ratio", text])
        assert built.value.args[0].drift_ratio == ratio
    assert main([*base, "--model", "auto"]) == 2
    assert "argument --model: invalid choice: 'auto'" in error_line(capsys)


def recorded_configs(monkeypatch):
    """The configs ``track shape`` builds its ``ShapeTracker`` with (the tracker runs as it would)."""
    import pipeline.track

    seen = []
    original = pipeline.track.ShapeTracker

    def tracker(robot, camera, config, **kwargs):
        seen.append(config)
        return original(robot, camera, config, **kwargs)

    monkeypatch.setattr(pipeline.track, "ShapeTracker", tracker)
    return seen


@pytest.mark.slow
def test_pcc_model_writes_each_frames_sections(sequence, tmp_path, monkeypatch):
    """``--model pcc --section-lengths ... --warm-pcc-iterations N``: every line has the frame's sections
    (``"pcc"``), and the options reach the tracker; the first frame's sections get the full fit's 50 (``pcc_iterations``)."""
    seen = recorded_configs(monkeypatch)
    folder, truths = sequence
    out = tmp_path / "traj.jsonl"
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--stop", "3", "--model", "pcc",
                 "--section-lengths", "0.1,0.1", "--warm-pcc-iterations", "5", "--out", str(out)) == 0
    config = seen[0]
    assert (config.full_fit.model, config.full_fit.section_lengths_m, config.warm_fit.pcc_iterations) == (
        "pcc", (0.1, 0.1), 5)
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == [0, 1, 2] and lines[-1]["summary"]
    for line in lines[:-1]:
        assert len(line["pcc"]["curvatures_per_m"]) == 2 and line["pcc"]["section_lengths_m"] == [0.1, 0.1]
        assert len(line["control_points_cam_m"]) == 3  # base, joint, tip
    assert [line["iterations"] for line in lines[:-1]] == [60 + 50, 10 + 5, 10 + 5]


class FakeCamera:
    """``cv2.VideoCapture(N)`` of a camera giving ``images`` in turn, one every ``period`` seconds (``None``: a
    failed read ends it; ``"interrupt"``: Ctrl-C while reading)."""

    def __init__(self, images, period=0.0, opens=True):
        self.images, self.period, self.opens, self.next_at = list(images), period, opens, None

    def __call__(self, index):
        self.index = index
        return self

    def isOpened(self):
        return self.opens

    def get(self, prop):
        return 0.0

    def grab(self):
        return self.read()[0]

    def read(self):
        import time

        self.next_at = time.perf_counter() if self.next_at is None else self.next_at + self.period
        time.sleep(max(0.0, self.next_at - time.perf_counter()))
        if not self.images:
            return False, None
        image = self.images.pop(0)
        if isinstance(image, str):
            raise KeyboardInterrupt
        return True, image

    def release(self):
        pass


def camera_images(folder, count):
    from pipeline.io import read_image

    return [read_image(folder / "frames" / f"{i % 4:05d}.png") for i in range(count)]


def mask_of_frame(folder, tmp_path, count):
    """Masks for frames 0..count-1 of a camera showing the sequence's 4 images in turn."""
    masks = tmp_path / "masks"
    masks.mkdir()
    for i in range(count):
        (masks / f"{i:05d}.png").write_bytes((folder / "masks" / f"{i % 4:05d}.png").read_bytes())
    return ["--mask-pattern", str(masks / "{frame:05d}.png")]


@pytest.mark.slow
def test_a_live_camera_is_tracked_as_its_frames_arrive(sequence, tmp_path, monkeypatch):
    """``--device N`` reads OpenCV's camera N in a background thread (``--live``): every frame gets its line, in
    order, with the seconds since the first frame; each fit takes the frames that arrived, at most
    ``--batch-frames``."""
    seen = recorded_configs(monkeypatch)
    folder, truths = sequence
    fake = FakeCamera(camera_images(folder, 6), period=0.05)
    monkeypatch.setattr(cv2, "VideoCapture", fake)
    out = tmp_path / "traj.jsonl"
    assert track(folder, "--device", "2", *mask_of_frame(folder, tmp_path, 6), "--batch-frames", "3",
                 "--out", str(out)) == 0
    assert fake.index == 2 and seen[0].live and seen[0].batch_frames == 3 and not seen[0].drop_late
    lines = read_lines(out)
    assert [line["frame"] for line in lines[:-1]] == list(range(6)) and lines[-1]["frames"] == 6
    assert all(line["skipped"] is None for line in lines[:-1])
    times = [line["time_s"] for line in lines[:-1]]
    assert times[0] == 0.0 and all(b > a for a, b in zip(times, times[1:])) and times[-1] >= 0.25
    for line in lines[:-1]:
        fitted = np.array(line["centerline_cam_m"])
        assert centerline_errors(fitted, truths[line["frame"] % 4], K)["mean_2d_px"] < 3.0


@pytest.mark.slow
def test_a_live_camera_faster_than_the_tracker_drops_late_frames_and_ctrl_c_ends_the_run(sequence, tmp_path,
                                                                                         monkeypatch):
    """``--drop-late``: frames that waited while the tracker was a batch behind get a ``dropped`` line (each frame
    one line, in order); Ctrl-C while reading ends the run with its summary, ``"interrupted": true``."""
    folder, _ = sequence
    images = camera_images(folder, 12) + ["interrupt"]
    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera(images, period=0.01))
    out = tmp_path / "traj.jsonl"
    assert track(folder, "--device", "0", *mask_of_frame(folder, tmp_path, 12), "--batch-frames", "2",
                 "--drop-late", "--out", str(out)) == 0
    lines = read_lines(out)
    summary = lines[-1]
    assert [line["frame"] for line in lines[:-1]] == list(range(12)) and summary["interrupted"] is True
    dropped = [line["frame"] for line in lines[:-1] if line["skipped"] and line["skipped"].startswith("dropped")]
    assert lines[0]["skipped"] is None and len(dropped) >= 4 and summary["skipped"] == len(dropped), dropped


def test_live_camera_errors_exit_2(sequence, tmp_path, monkeypatch, capsys):
    folder, _ = sequence
    monkeypatch.setattr(cv2, "VideoCapture", FakeCamera([], opens=False))
    assert track(folder, "--device", "7") == 2
    assert "--device 7: OpenCV cannot open camera 7" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--drop-late") == 2
    assert "--drop-late drops the frames of a live source: add --live (or read a --device)" in error_line(capsys)


def test_bad_input_exits_2_with_one_line(sequence, tmp_path, capsys):
    folder, _ = sequence
    assert track(folder, "--frames", str(tmp_path / "none" / "*.png")) == 2
    assert "no file matches" in error_line(capsys)
    empty = tmp_path / "empty.mp4"
    empty.write_bytes(b"")
    assert track(folder, "--video", str(empty)) == 2
    assert "--video" in error_line(capsys)
    assert track(folder, "--video", str(tmp_path / "missing.mp4")) == 2
    assert "no such file" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--step", "0") == 2
    assert "--step" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-hypotheses", "one") == 2
    assert "--warm-hypotheses: expected 'none' or indices" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--batch-frames", "0") == 2
    assert "batch_frames: expected an int >= 1" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--rim-search-frames", "0") == 2
    assert "rim_search_frames: expected an int >= 1" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--batch-frames", "4", "--compile") == 2
    assert "batch_frames > 1 with warm_fit.compile" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-pcc-iterations", "5") == 2
    assert "--warm-pcc-iterations is an option of --model pcc, but --model is bezier" in error_line(capsys)
    assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--model", "pcc", "--warm-pcc-iterations",
                 "0") == 2
    assert "pcc_iterations: expected an int >= 1" in error_line(capsys)
    for bad in ("abc", "0.5"):
        assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--drift-ratio", bad) == 2
        err = error_line(capsys)
        assert "drift" in err and "> 1" in err and bad in err, err
    for bad in ("-0.5", "nan"):
        assert track(folder, "--frames", str(folder / "frames" / "*.png"), "--warm-slow-start", bad) == 2
        assert "warm_slow_start" in error_line(capsys)


@pytest.mark.slow
def test_missing_mask_stops_the_run_keeping_the_lines_written(sequence, tmp_path, capsys):
    folder, _ = sequence
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "00000.png").write_bytes((folder / "masks" / "00000.png").read_bytes())
    out = tmp_path / "traj.jsonl"
    code = main(["track", "shape", "--camera", str(folder / "camera.json"), *ARM, *QUICK, "--frames",
                 str(folder / "frames" / "*.png"), "--segmenter", "file", "--mask-pattern",
                 str(masks / "{frame:05d}.png"), "--out", str(out)])
    assert code == 2
    assert "00001.png" in error_line(capsys)
    assert [line["frame"] for line in read_lines(out)] == [0]
