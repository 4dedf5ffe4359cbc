"""``pipeline.batch`` / ``pipeline batch``: manifest validation, and engines whose results equal the single-item
commands' (run in this process through ``pipeline.cli.main``), resume, failures recorded, shards."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import batch
from pipeline.camera import Camera
from pipeline.cli import main
from pipeline.errors import ConfigError
from pipeline.io import write_image, write_json, write_mask
from pipeline.shapes.polyline import bezier_centerline
from pipeline.synth.soft_arm import moving_bezier_arm, render_tube_image

REPO = Path(__file__).resolve().parents[1]
TOY = REPO / "data" / "toy_arm"
ARM = REPO / "data" / "soft_arm" / "quadratic"
URDF = REPO / "models" / "robots" / "toy_arm_mesh" / "toy_arm_mesh.urdf"
JOINTS = json.loads((TOY / "joints.json").read_text())
POSE_QUICK = {"iterations": 20, "starts": 2, "working_max_side": 160, "polish_rounds": 2, "polish_newton_steps": 1}
SHAPE_QUICK = {"iterations": 20, "starts": 2}
TRACK_QUICK = {"order": 2, "iterations": 20, "starts": 1, "warm_iterations": 5, "warm_prefit_iterations": 20}
POSE_TRACK_QUICK = {**POSE_QUICK, "warm_iterations": 5, "warm_max_side": 160, "warm_newton_steps": 1,
                    "static_camera": True, "static_iterations": 5}
TRACK_H, TRACK_W = 120, 200
TRACK_TIMING = ("seconds", "fps")  # keys ending so are timings


def pose_entry(item_id, **extra):
    return {"id": item_id, "command": "pose", "camera": str(TOY / "camera.json"), "mask": str(TOY / "mask.png"),
            "robot": str(URDF), "root": "base_link", "joints": JOINTS, "options": dict(POSE_QUICK), **extra}


def shape_entry(item_id, mask=ARM / "mask.png"):
    return {"id": item_id, "command": "shape", "camera": str(ARM / "camera.json"), "mask": str(mask),
            "length": 0.2, "base_radius": 0.014, "tip_radius": 0.006, "options": dict(SHAPE_QUICK)}


def make_sequence(folder, frames=3):
    """``frames`` images and masks of a moving soft arm and their camera under ``folder`` (``frames/``,
    ``masks/``, ``camera.json``)."""
    K = np.array([[110.0, 0.0, (TRACK_W - 1) / 2], [0.0, 110.0, (TRACK_H - 1) / 2], [0.0, 0.0, 1.0]])
    for i, control in enumerate(moving_bezier_arm(np.random.default_rng(3), K, (TRACK_H, TRACK_W), frames,
                                                  period_frames=40.0)):
        image, mask = render_tube_image(bezier_centerline(control, 201), np.linspace(0.014, 0.006, 201), K,
                                        (TRACK_H, TRACK_W), np.random.default_rng(0))
        write_image(folder / "frames" / f"{i:05d}.png", image)
        write_mask(folder / "masks" / f"{i:05d}.png", mask)
    write_json(folder / "camera.json", Camera(K=K.tolist(), width=TRACK_W, height=TRACK_H).to_dict())
    return folder


def track_entry(item_id, sequence="seq"):
    """A ``track shape`` item with paths relative to the manifest's folder (``sequence`` is a folder there)."""
    return {"id": item_id, "command": "track shape", "camera": f"{sequence}/camera.json",
            "frames": f"{sequence}/frames/*.png", "segmenter": "file",
            "mask_pattern": f"{sequence}/masks/{{frame:05d}}.png", "length": 0.2, "base_radius": 0.014,
            "tip_radius": 0.006, "options": dict(TRACK_QUICK)}


def make_pose_sequence(folder, frames=3):
    """``frames`` masks of the toy arm (joints moving, static camera; the painter's renderer), their images,
    ``joints.csv`` and ``camera.json`` under ``folder``."""
    from pipeline.robots import load_robot
    from pipeline.synth.pose import manipulator_sequence, painter_mask, render_robot_image

    camera = Camera(K=((170.0, 0.0, (TRACK_W - 1) / 2), (0.0, 170.0, (TRACK_H - 1) / 2), (0.0, 0.0, 1.0)),
                    width=TRACK_W, height=TRACK_H)
    model = load_robot(URDF, "base_link")
    joints, poses = manipulator_sequence(model, camera, np.random.default_rng(1), frames, fill_range=(0.85, 0.95))
    for i, (q, T) in enumerate(zip(joints, poses)):
        write_image(folder / "frames" / f"{i:05d}.png", render_robot_image(model, q, T, camera,
                                                                           np.random.default_rng(0))[0])
        write_mask(folder / "masks" / f"{i:05d}.png", painter_mask(model, q, T, camera))
    rows = ["frame," + ",".join(model.joint_names)] + [f"{i}," + ",".join(map(str, q)) for i, q in enumerate(joints)]
    (folder / "joints.csv").write_text("\n".join(rows) + "\n")
    write_json(folder / "camera.json", camera.to_dict())
    return folder


def pose_track_entry(item_id, sequence="pseq"):
    """A ``track pose`` item with paths relative to the manifest's folder, joints from its CSV file."""
    return {"id": item_id, "command": "track pose", "camera": f"{sequence}/camera.json",
            "frames": f"{sequence}/frames/*.png", "segmenter": "file",
            "mask_pattern": f"{sequence}/masks/{{frame:05d}}.png", "robot": str(URDF), "root": "base_link",
            "joints_csv": f"{sequence}/joints.csv", "options": dict(POSE_TRACK_QUICK)}


def read_jsonl(path):
    return [json.loads(line) for line in Path(path).read_text().splitlines()]


def write_manifest(path, entries):
    path.write_text("".join((e if isinstance(e, str) else json.dumps(e)) + "\n" for e in entries))
    return path


def without_seconds(value):
    if isinstance(value, dict):
        return {k: without_seconds(v) for k, v in value.items() if not k.endswith(TRACK_TIMING)}
    if isinstance(value, list):
        return [without_seconds(v) for v in value]
    return value


# ---------------------------------------------------------------------------------------------------------------
# Manifest


def test_item_argv_is_the_single_commands_argv_with_paths_resolved(tmp_path):
    (tmp_path / "cam").mkdir()
    shutil.copy(TOY / "camera.json", tmp_path / "cam" / "c.json")
    shutil.copy(TOY / "mask.png", tmp_path / "m.png")
    entry = {"id": 7, "command": "pose", "camera": "cam/c.json", "mask": "m.png", "urdf": str(URDF),
             "root": "base_link", "joints": {"joint1": 0.1, "joint2": -2}, "zero-missing": True,
             "options": {"iterations": 30, "package": ["p=meshes", "q=/abs"], "tip": None}}
    manifest = write_manifest(tmp_path / "m.jsonl", ["# a comment", "", entry])
    (item,) = batch.read_manifest(manifest)
    assert item.id == "7" and item.command == "pose" and item.line == 3
    assert item.argv == ("--camera", str(tmp_path / "cam" / "c.json"), "--mask", str(tmp_path / "m.png"),
                         "--robot", str(URDF), "--root", "base_link", "--joints", "joint1=0.1,joint2=-2.0",
                         "--zero-missing", "--iterations", "30", "--package", f"p={tmp_path / 'meshes'}",
                         "--package", "q=/abs")


def test_robot_key_maps_to_the_pose_commands_robot_option():
    parser = batch._command_parser("pose")
    actions = batch._option_actions(parser)
    expected = "robot"
    assert "robot" in actions
    assert batch.robot_option(actions, "robot") == expected
    assert batch.robot_option(actions, "urdf") == expected
    item = batch.item_from_dict(pose_entry("a"), REPO)
    assert item.argv[item.argv.index("--" + expected) + 1] == str(URDF)


def test_every_bad_line_is_reported_with_its_number_before_any_work(tmp_path):
    entries = [
        pose_entry("ok"),
        '{"id": "x", "command": "pose",',  # line 2: not JSON
        shape_entry("ok"),  # line 3: duplicate id
        {**shape_entry("s"), "colour": "red"},  # line 4: unknown option
        {**pose_entry("t"), "command": "track"},  # line 5: no such command
        {**shape_entry("u"), "mask": "missing.png"},  # line 6: missing file, relative to the manifest
        {k: v for k, v in shape_entry("v").items() if k != "length"},  # line 7: the command's own parser
        {**shape_entry("w"), "options": {"out": "x.json"}},  # line 8: outputs belong to the batch
        {**shape_entry("../y")},  # line 9: an id that is not a folder name
        [1, 2],  # line 10: not an object
    ]
    manifest = write_manifest(tmp_path / "m.jsonl", entries)
    with pytest.raises(ConfigError) as info:
        batch.read_manifest(manifest)
    message = str(info.value)
    assert "9 bad line(s)" in message and "line 1:" not in message
    for needle in ("line 2: not valid JSON", "line 3: id 'ok' is already used on line 1", "line 4: unknown option "
                   "'colour' for shape",
                   "line 5: command: expected one of pose, shape, track shape, track pose, got 'track'",
                   f"line 6: mask: file not found: {tmp_path / 'missing.png'}", "line 7:", "--length",
                   "line 8: out: the batch writes the outputs itself", "line 9: id:", "line 10: expected a JSON "
                   "object"):
        assert needle in message, message


def test_cli_reports_a_malformed_line_with_exit_2(tmp_path, capsys):
    manifest = write_manifest(tmp_path / "m.jsonl", [shape_entry("a"), "{not json"])
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "line 2: not valid JSON" in err, err
    assert not (tmp_path / "out").exists()


def test_shards_take_every_nth_item():
    items = [batch.item_from_dict(shape_entry(f"s{i}"), REPO) for i in range(7)]
    shards = [batch.select_shard(items, i, 3) for i in range(3)]
    assert [[it.id for it in shard] for shard in shards] == [["s0", "s3", "s6"], ["s1", "s4"], ["s2", "s5"]]
    assert batch.parse_shard("2/3") == (2, 3)
    for bad in ("3/3", "-1/2", "1", "a/b", "0/0"):
        with pytest.raises(ConfigError, match="--shard: expected i/N"):
            batch.parse_shard(bad)


def test_missing_ray_is_an_exit_2_error_saying_how_to_install(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    manifest = write_manifest(tmp_path / "m.jsonl", [shape_entry("a")])
    assert main(["batch", str(manifest), "--out", str(tmp_path / "out"), "--engine", "ray"]) == 2
    err = capsys.readouterr().err
    assert "needs Ray" in err and "pip install" in err and "[ray]" in err, err


def test_track_item_resolves_its_frames_against_the_manifest_and_is_finished_only_with_its_summary(tmp_path):
    make_sequence(tmp_path / "seq", frames=2)
    entry = {**track_entry("t"), "options": {**TRACK_QUICK, "video": None}}
    manifest = write_manifest(tmp_path / "m.jsonl", [entry])
    (item,) = batch.read_manifest(manifest)
    argv = dict(zip(item.argv[::2], item.argv[1::2]))
    assert argv["--camera"] == str(tmp_path / "seq" / "camera.json")
    assert argv["--frames"] == str(tmp_path / "seq" / "frames" / "*.png")
    assert argv["--mask-pattern"] == str(tmp_path / "seq" / "masks" / "{frame:05d}.png")
    assert batch.COMMANDS["track shape"].result_file == "result.jsonl"

    frame = {"frame": 0, "loss": 0.5, "skipped": None}
    summary = {"summary": True, "frames": 2, "skipped": 1, "reinitialisations": 0, "fps": 3.0, "seconds": 0.7}
    (tmp_path / "out" / "t").mkdir(parents=True)
    result = tmp_path / "out" / "t" / "result.jsonl"
    result.write_text(json.dumps(frame) + "\n")  # a track stopped before its summary line
    assert not batch.is_finished(item, tmp_path / "out")
    result.write_text("".join(json.dumps(line) + "\n" for line in
                              (frame, {"frame": 1, "loss": None, "skipped": "no robot"}, summary)))
    assert batch.is_finished(item, tmp_path / "out")
    (skipped,) = batch.run([item], tmp_path / "out", resume=True, progress=False)
    assert skipped.status == "skipped" and skipped.loss == 0.5
    assert skipped.figures == {"frames": 2, "skipped": 1, "reinitialisations": 0, "fps": 3.0, "last_loss": 0.5}


def test_track_items_refuse_output_options_and_a_frames_glob_matching_nothing(tmp_path):
    make_sequence(tmp_path / "seq", frames=1)
    entries = [{**track_entry("a"), "overlay_video": "x.mp4"}, {**track_entry("b"), "frames": "seq/none/*.png"},
               {**pose_track_entry("c", sequence="seq"), "joints_csv": "seq/none.csv"}]
    with pytest.raises(ConfigError) as info:
        batch.read_manifest(write_manifest(tmp_path / "m.jsonl", entries))
    message = str(info.value)
    for needle in ("line 1: overlay_video: the batch writes the outputs itself (OUT/<id>/result.jsonl, overlay.mp4)",
                   f"line 2: frames: no file matches {str(tmp_path / 'seq' / 'none' / '*.png')!r}",
                   f"line 3: joints_csv: file not found: {tmp_path / 'seq' / 'none.csv'}"):
        assert needle in message, message


def test_write_item_replaces_files_and_leaves_no_temporary_ones(tmp_path):
    result = batch.ItemResult(id="a", command="shape", status="done", loss=1.0,
                              files={"result.json": b'{"loss": 1.0}', "overlay.png": b"png"})
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "error.txt").write_text("an earlier failure")
    written = batch.write_item(result, tmp_path)
    assert written.files == {} and written.loss == 1.0
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["overlay.png", "result.json"]
    assert (tmp_path / "a" / "result.json").read_bytes() == b'{"loss": 1.0}'
    item = batch.item_from_dict(shape_entry("a"), REPO)
    assert batch.is_finished(item, tmp_path)
    failed = batch.ItemResult(id="b", command="shape", status="failed", error="boom")
    batch.write_item(failed, tmp_path)
    assert (tmp_path / "b" / "error.txt").read_text() == "boom"
    assert not batch.is_finished(batch.item_from_dict(shape_entry("b"), REPO), tmp_path)


# ---------------------------------------------------------------------------------------------------------------
# Engines against the single-item commands


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """A manifest of a pose item, a shape item, a short ``track shape`` item (3 frames, paths relative to the
    manifest) and a failing one (a mask of the wrong size), with the single commands' outputs for the good ones
    (``pipeline track shape`` run directly for the track)."""
    folder = tmp_path_factory.mktemp("batch")
    make_sequence(folder / "seq")
    make_pose_sequence(folder / "pseq")
    entries = [pose_entry("pose-1"), shape_entry("shape-1"), track_entry("track-1"),
               shape_entry("bad", mask=TOY / "mask.png"), pose_track_entry("track-pose-1")]
    manifest = write_manifest(folder / "manifest.jsonl", entries)
    items = batch.read_manifest(manifest)
    reference = {}
    for item in items[:2]:
        out, overlay = folder / f"{item.id}.json", folder / f"{item.id}.png"
        assert main([item.command, *item.argv, "--out", str(out), "--overlay", str(overlay)]) == 0
        reference[item.id] = (json.loads(out.read_text()), overlay.read_bytes())
    out, overlay = folder / "track-1.jsonl", folder / "track-1.mp4"
    assert main(["track", "shape", "--camera", str(folder / "seq" / "camera.json"), "--frames",
                 str(folder / "seq" / "frames" / "*.png"), "--segmenter", "file", "--mask-pattern",
                 str(folder / "seq" / "masks" / "{frame:05d}.png"), "--length", "0.2", "--base-radius", "0.014",
                 "--tip-radius", "0.006", "--order", "2", "--iterations", "20", "--starts", "1",
                 "--warm-iterations", "5", "--warm-prefit-iterations", "20", "--quiet", "--out", str(out),
                 "--overlay-video", str(overlay)]) == 0
    reference["track-1"] = (read_jsonl(out), overlay.read_bytes())
    out, overlay = folder / "track-pose-1.jsonl", folder / "track-pose-1.mp4"
    assert main(["track", "pose", *items[4].argv, "--quiet", "--out", str(out), "--overlay-video", str(overlay)]) == 0
    reference["track-pose-1"] = (read_jsonl(out), overlay.read_bytes())
    return items, reference


def check_same_as_single_commands(results, out_dir, reference):
    by_id = {r.id: r for r in results}
    assert sorted(by_id) == ["bad", "pose-1", "shape-1", "track-1", "track-pose-1"]
    for item_id, (expected, overlay) in reference.items():
        assert by_id[item_id].status in ("done", "skipped")
        if item_id == "track-pose-1":
            got = read_jsonl(out_dir / item_id / "result.jsonl")
            assert without_seconds(got) == without_seconds(expected)
            assert len(got) == 4 and got[-1]["static_camera"]["frames"] == [0, 1, 2]
            assert (out_dir / item_id / "overlay.mp4").read_bytes() == overlay
            T = expected[-1]["T_cam_root"]
            assert by_id[item_id].figures["static_t_cam_root_m"] == [T[0][3], T[1][3], T[2][3]]
            continue
        if item_id == "track-1":
            got = read_jsonl(out_dir / item_id / "result.jsonl")
            assert without_seconds(got) == without_seconds(expected)
            assert (out_dir / item_id / "overlay.mp4").read_bytes() == overlay
            losses = [line["loss"] for line in expected[:-1]]
            assert len(losses) == 3 and by_id[item_id].loss == pytest.approx(sum(losses) / 3)
            summary = expected[-1]
            assert {k: by_id[item_id].figures[k] for k in ("frames", "skipped", "reinitialisations")} == {
                k: summary[k] for k in ("frames", "skipped", "reinitialisations")}
            assert by_id[item_id].figures["last_loss"] == losses[-1] and by_id[item_id].figures["fps"] > 0
            continue
        got = json.loads((out_dir / item_id / "result.json").read_text())
        assert without_seconds(got) == without_seconds(expected)
        assert (out_dir / item_id / "overlay.png").read_bytes() == overlay
        assert by_id[item_id].loss == expected["loss"]
    assert by_id["bad"].status == "failed" and "800x600" in by_id["bad"].error
    assert "800x600" in (out_dir / "bad" / "error.txt").read_text()
    assert not (out_dir / "bad" / "result.json").exists()
    assert not list(out_dir.rglob("*.tmp"))


@pytest.mark.slow
def test_local_engine_equals_single_commands_and_resume_skips_done_items(mixed, tmp_path):
    items, reference = mixed
    out_dir = tmp_path / "out"
    results = list(batch.run(items, out_dir, engine="local", workers=2, progress=False))
    check_same_as_single_commands(results, out_dir, reference)

    shutil.rmtree(out_dir / "shape-1")
    before = (out_dir / "pose-1" / "result.json").stat().st_mtime_ns
    track_before = (out_dir / "track-1" / "result.jsonl").stat().st_mtime_ns
    again = {r.id: r for r in batch.run(items, out_dir, engine="local", workers=1, resume=True, progress=False)}
    assert again["pose-1"].status == "skipped" and again["pose-1"].loss == reference["pose-1"][0]["loss"]
    assert (out_dir / "pose-1" / "result.json").stat().st_mtime_ns == before
    assert again["track-1"].status == "skipped" and again["track-1"].figures["frames"] == 3
    assert again["track-1"].loss == results[[r.id for r in results].index("track-1")].loss
    assert (out_dir / "track-1" / "result.jsonl").stat().st_mtime_ns == track_before
    assert again["shape-1"].status == "done" and again["bad"].status == "failed"  # failures are tried again
    check_same_as_single_commands(again.values(), out_dir, reference)


@pytest.mark.slow
def test_cli_batch_writes_summary_and_exits_1_when_an_item_failed(mixed, tmp_path, capsys):
    items, reference = mixed
    manifest = write_manifest(tmp_path / "m.jsonl", [pose_entry("pose-1"), shape_entry("bad", mask=TOY / "mask.png")])
    out_dir = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out_dir), "--workers", "2", "--no-progress"]) == 1
    stdout = capsys.readouterr().out
    assert "2 items: 1 done, 1 failed, 0 skipped" in stdout and "FAILED bad:" in stdout
    lines = [json.loads(line) for line in (out_dir / "summary.jsonl").read_text().splitlines()]
    assert [(line["id"], line["status"]) for line in lines] == [("pose-1", "done"), ("bad", "failed")]
    T = reference["pose-1"][0]["T_cam_root"]
    assert lines[0]["loss"] == reference["pose-1"][0]["loss"]
    assert lines[0]["t_cam_root_m"] == [T[0][3], T[1][3], T[2][3]]
    assert "800x600" in lines[1]["error"]


@pytest.fixture(scope="module")
def ray_session():
    ray = pytest.importorskip("ray", reason="Ray is not installed (pip install '.[ray]'); the Ray engine is untested")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow
def test_ray_engine_equals_single_commands(mixed, ray_session, tmp_path):
    items, reference = mixed
    out_dir = tmp_path / "out"
    results = list(batch.run(items, out_dir, engine="ray", progress=False))
    check_same_as_single_commands(results, out_dir, reference)


def test_ray_is_imported_only_for_the_ray_engine(tmp_path):
    import subprocess

    manifest = write_manifest(tmp_path / "m.jsonl", [shape_entry("a")])
    code = ("import sys; from pipeline import batch; from pipeline.cli import build_parser; build_parser(); "
            f"batch.read_manifest({str(manifest)!r}); print('ray' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


@pytest.mark.slow
def test_cli_shard_runs_every_nth_item_and_writes_its_own_summary(tmp_path, capsys):
    quick = {"iterations": 3, "starts": 1}
    entries = [{**shape_entry(f"s{i}"), "options": quick} for i in range(3)]
    manifest = write_manifest(tmp_path / "m.jsonl", entries)
    out_dir = tmp_path / "out"
    assert main(["batch", str(manifest), "--out", str(out_dir), "--shard", "1/2", "--workers", "1",
                 "--no-progress"]) == 0
    assert sorted(p.name for p in out_dir.iterdir()) == ["s1", "summary-shard-1-of-2.jsonl"]
    lines = (out_dir / "summary-shard-1-of-2.jsonl").read_text().splitlines()
    assert [json.loads(line)["id"] for line in lines] == ["s1"]
    assert "1 items: 1 done" in capsys.readouterr().out


def test_a_worker_loads_each_robot_model_once_and_gives_the_same_results(tmp_path, monkeypatch):
    """Items in one worker process share the robot model loaded for the first (keyed by the description file, its
    modification time and the load options); a different option loads again; results equal uncached ones."""
    import json as json_module

    import pipeline.robots.manipulator as manipulator

    calls = []
    original = manipulator.load_robot

    def counting(*args, **kwargs):
        calls.append((args, tuple(sorted(kwargs))))
        return original(*args, **kwargs)

    monkeypatch.setattr(manipulator, "load_robot", counting)
    monkeypatch.setattr(batch, "_model_cache", {})
    items = [batch.item_from_dict(pose_entry(name), REPO) for name in ("a", "b")]
    first, second = (batch.run_cli_item(item) for item in items)
    assert first.status == second.status == "done" and len(calls) == 1
    other = batch.item_from_dict(pose_entry("c", primitive="hull"), REPO)
    assert batch.run_cli_item(other).status == "done" and len(calls) == 2  # another primitive: loaded again

    def without_timing(result):
        content = json_module.loads(result.files[batch.RESULT_FILE])
        return {k: v for k, v in content.items() if "seconds" not in k}

    monkeypatch.setattr(batch, "_model_cache", {})
    fresh = batch.run_cli_item(items[1])
    assert without_timing(fresh) == without_timing(second)
