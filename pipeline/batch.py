"""Batch runs: many single-command items (a JSON-lines manifest) in a local ``spawn`` process pool or as Ray tasks.

Each item is one run of a single-item command (``pose``, ``shape``, ``track shape``, ``track pose``), written in
that command's vocabulary and turned into its argv: the worker parses it with the command's own parser and calls the
command's own function in-process, so a batch result is the single command's result by construction. Workers write
into a private temporary folder and send the files' bytes back; the driver writes ``OUT/<id>/result.json``
(``result.jsonl`` for the tracks) and the overlay (``overlay.png``, ``overlay.mp4``) through a temporary file and a
rename (an interrupted run never leaves half a result; ``resume`` skips items whose complete result file exists),
``OUT/<id>/error.txt`` for a failed item, and ``OUT/summary.jsonl`` at the end.

Manifest line (JSON object), keys besides ``id``, ``command`` and ``options`` being options too::

    {"id": "ep001", "command": "pose", "camera": "cam.json", "mask": "ep001/mask.png", "urdf": "arm.urdf",
     "root": "base_link", "joints": {"joint1": 0.3, "joint2": -1.2}, "options": {"iterations": 300}}

Option names are the command's long options without the dashes (``joints_file`` or ``joints-file``); ``true``
gives a flag, ``false``/``null`` leaves the option out, a list repeats it (``package``), ``joints`` may be an
object. Relative paths (and the ``frames`` glob, the ``mask_pattern``) resolve against the manifest's folder.
``out``, ``overlay``, ``overlay_video`` and ``history`` belong to the batch and are refused.

Python::

    items = read_manifest("manifest.jsonl")
    losses = {result.id: result.loss for result in run(items, "out/", engine="local", workers=2)
              if result.status == "done"}

Layer: the batch sits with the CLI (it reuses the command modules' parsers and functions); Ray is imported only for
``engine="ray"``.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import glob
import io
import json
import logging
import os
import re
import tempfile
import time
import traceback
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

from pipeline.errors import AssetError, ConfigError, PipelineError

log = logging.getLogger(__name__)

ENGINES = ("local", "ray")
STATUSES = ("done", "failed", "skipped")
RESULT_FILE = "result.json"
TRACK_RESULT_FILE = "result.jsonl"
OVERLAY_FILE = "overlay.png"
OVERLAY_VIDEO_FILE = "overlay.mp4"
ERROR_FILE = "error.txt"
RAY_INSTALL_HINT = "pip install 'robot-state-from-image[ray]' (or: pip install ray)"


def _pose_figures(result: dict) -> dict:
    T = result["T_cam_root"]
    return {"t_cam_root_m": [T[0][3], T[1][3], T[2][3]], "iterations": result.get("iterations")}


def _shape_figures(result: dict) -> dict:
    return {"tip_cam_m": result["centerline_cam_m"][-1], "iterations": result.get("iterations")}


def _read_json(data: bytes) -> dict:
    return json.loads(data)


def _read_track(data: bytes) -> dict:
    """A ``track shape`` or ``track pose`` JSONL -> its summary line with ``loss`` (the mean loss of the tracked
    frames) and ``last_loss`` (the last tracked frame's); ValueError when the summary line is missing (an unfinished track)."""
    lines = [json.loads(line) for line in data.decode("utf-8").splitlines() if line.strip()]
    if not lines or lines[-1].get("summary") is not True:
        raise ValueError("no summary line: the track did not finish")
    losses = [line["loss"] for line in lines[:-1] if line.get("loss") is not None]
    return {**lines[-1], "loss": sum(losses) / len(losses) if losses else None,
            "last_loss": losses[-1] if losses else None}


def _track_figures(result: dict) -> dict:
    figures = {"frames": result["frames"], "skipped": result["skipped"],
               "reinitialisations": result["reinitialisations"], "fps": result["fps"], "last_loss": result["last_loss"]}
    if "static_camera" in result:  # track pose --static-camera: the joint estimate's translation
        T = result["T_cam_root"]
        figures["static_t_cam_root_m"] = [T[0][3], T[1][3], T[2][3]]
    return figures


@dataclasses.dataclass(frozen=True, kw_only=True)
class Command:
    """How the batch runs one kind of item.

    argv: the words that select the command (``("pose",)``, ``("track", "shape")``).
    result_file: its result's name in ``OUT/<id>/`` (the command's ``--out``).
    figures: the key figures of its result (as ``read`` gives it) for the summary.
    read: the result file's bytes -> a dict with ``loss`` and what ``figures`` needs; raises ValueError (or
        KeyError, ...) for an unfinished result (default: the JSON object).
    overlay_option, overlay_file: the command's overlay option and the overlay's name in ``OUT/<id>/``.
    extra_argv: words added to every run (``--quiet``: no progress bars from the workers).
    worker: runs one item in a worker process (default ``run_cli_item``: the command's own function).
    """

    argv: tuple[str, ...]
    result_file: str
    figures: Callable[[dict], dict]
    read: Callable[[bytes], dict] = _read_json
    overlay_option: str = "--overlay"
    overlay_file: str = OVERLAY_FILE
    extra_argv: tuple[str, ...] = ()
    worker: Callable[..., ItemResult] | None = None


#: Item kinds the batch runs: command name -> how.
COMMANDS: dict[str, Command] = {
    "pose": Command(argv=("pose",), result_file=RESULT_FILE, figures=_pose_figures),
    "shape": Command(argv=("shape",), result_file=RESULT_FILE, figures=_shape_figures),
    "track shape": Command(argv=("track", "shape"), result_file=TRACK_RESULT_FILE, figures=_track_figures,
                           read=_read_track, overlay_option="--overlay-video", overlay_file=OVERLAY_VIDEO_FILE,
                           extra_argv=("--quiet",)),
    "track pose": Command(argv=("track", "pose"), result_file=TRACK_RESULT_FILE, figures=_track_figures,
                          read=_read_track, overlay_option="--overlay-video", overlay_file=OVERLAY_VIDEO_FILE,
                          extra_argv=("--quiet",)),
}

# Options that name a file or folder (resolved against the manifest's folder; the first group must exist).
_EXISTING_PATH_OPTIONS = ("camera", "mask", "image", "video", "urdf", "robot", "joints_file", "joints_csv")
_PATTERN_OPTIONS = ("frames", "mask_pattern")
_RESERVED_OPTIONS = ("out", "overlay", "overlay_video", "history")
_ITEM_KEYS = ("id", "command", "options")
_ID = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]*$")


@dataclasses.dataclass(frozen=True, kw_only=True)
class BatchItem:
    """One item: a single command's run, with its argv (absolute paths, no output options).

    id: the item's name and its folder under the output folder (letters, digits, ``_ . -``).
    command: a key of ``COMMANDS``.
    argv: the command's options, e.g. ``("--camera", "/data/cam.json", "--mask", ...)``.
    line: the manifest line it came from (0 when made in Python).
    """

    id: str
    command: str
    argv: tuple[str, ...]
    line: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.id, str) or not _ID.match(self.id):
            raise ConfigError(f"id: expected letters, digits, '_', '.' or '-' (not starting with '.' or '-'), "
                              f"usable as a folder name, got {self.id!r}")
        _check_command(self.command)
        if not isinstance(self.argv, tuple) or not all(isinstance(a, str) for a in self.argv):
            raise ConfigError(f"argv: expected a tuple of strings, got {self.argv!r}")
        if not isinstance(self.line, int) or self.line < 0:
            raise ConfigError(f"line: expected an integer >= 0, got {self.line!r}")


@dataclasses.dataclass(frozen=True, kw_only=True)
class ItemResult:
    """The outcome of one item.

    status: ``done``, ``failed`` or ``skipped`` (finished by an earlier run, with ``resume``).
    seconds: wall time of the item in its worker (0 when skipped).
    loss: the fit's final loss (None when failed).
    figures: the command's key figures (translation of T_cam_root, tip position, iterations).
    error: the error message when failed (a traceback for an unexpected exception).
    message: what the command printed.
    files: the output files' names and bytes, as the worker made them (empty once the driver wrote them).
    """

    id: str
    command: str
    status: str
    seconds: float = 0.0
    loss: float | None = None
    figures: dict = dataclasses.field(default_factory=dict)
    error: str | None = None
    message: str = ""
    files: dict = dataclasses.field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ConfigError(f"status: expected one of {', '.join(STATUSES)}, got {self.status!r}")
        if self.status == "failed" and not self.error:
            raise ConfigError("error: a failed item needs its error message")

    def summary(self) -> dict:
        """The item's line in ``summary.jsonl``."""
        line = {"id": self.id, "command": self.command, "status": self.status, "seconds": round(self.seconds, 3),
                "loss": self.loss, **self.figures}
        if self.error is not None:
            line["error"] = self.error.strip().splitlines()[-1] if self.error.strip() else self.error
        return line


def _check_command(command: object) -> None:
    if command not in COMMANDS:
        raise ConfigError(f"command: expected one of {', '.join(COMMANDS)}, got {command!r}")


# ---------------------------------------------------------------------------------------------------------------
# Manifest -> items


def _command_parser(command: str) -> argparse.ArgumentParser:
    """The argparse parser of ``command`` (a key of ``COMMANDS``), as the CLI builds it."""
    from pipeline.cli import build_parser

    parser = build_parser()
    for word in COMMANDS[command].argv:
        subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        parser = subparsers.choices[word]
    return parser


def _option_actions(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """Long option name without dashes, with ``_`` for ``-`` -> its action."""
    actions = {}
    for action in parser._actions:
        for flag in action.option_strings:
            if flag.startswith("--") and flag != "--help":
                actions[flag[2:].replace("-", "_")] = action
    return actions


def robot_option(actions: dict[str, argparse.Action], key: str) -> str:
    """The option a manifest's ``robot`` or ``urdf`` key becomes: ``--robot`` (``--urdf`` is its alias)."""
    return "robot"


def _resolve(value: str, base: Path) -> str:
    path = Path(value).expanduser()
    return str(path if path.is_absolute() else base / path)


def _option_words(name: str, value: object, action: argparse.Action, base: Path) -> list[str]:
    """One manifest option -> argv words (paths resolved against ``base``)."""
    flag = next(f for f in action.option_strings if f.startswith("--"))
    if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: a flag; expected true or false, got {json.dumps(value)}")
        return [flag] if value else []
    if value is None or value is False:
        return []
    if isinstance(value, list):
        if not isinstance(action, argparse._AppendAction):
            raise ConfigError(f"{name}: expected one value, got a list (only repeatable options take lists)")
        return [word for v in value for word in _option_words(name, v, _single(action), base)]
    if name == "joints" and isinstance(value, dict):
        value = ",".join(f"{joint}={_number(joint, v)!r}" for joint, v in value.items())
    if isinstance(value, (dict, bool)):
        raise ConfigError(f"{name}: expected a string or a number, got {json.dumps(value)}")
    text = repr(value) if isinstance(value, float) else str(value)
    if name in _EXISTING_PATH_OPTIONS or name in _PATTERN_OPTIONS:
        text = _resolve(text, base)
        if name in _EXISTING_PATH_OPTIONS and not Path(text).exists():
            raise AssetError(f"{name}: file not found: {text}")
        if name == "frames" and not glob.glob(text):
            raise AssetError(f"frames: no file matches {text!r}")
    elif name == "package":
        package, sep, folder = text.partition("=")
        text = f"{package}={_resolve(folder, base)}" if sep else text
    elif name == "onnx_model" and ("/" in text or text.endswith(".onnx")):
        text = _resolve(text, base)
    return [flag, text]


def _single(action: argparse.Action) -> argparse.Action:
    return argparse._StoreAction(option_strings=action.option_strings, dest=action.dest)


def _number(joint: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"joints: {joint!r} needs a number, got {json.dumps(value)}")
    return float(value)


def item_from_dict(entry: dict, base: str | Path, *, line: int = 0) -> BatchItem:
    """One manifest entry -> a validated ``BatchItem`` (its argv parsed by the command's own parser).

    base: the folder relative paths resolve against (the manifest's). Raises ConfigError / AssetError.
    """
    if not isinstance(entry, dict):
        raise ConfigError(f"expected a JSON object, got {type(entry).__name__}")
    for key in ("id", "command"):
        if key not in entry:
            raise ConfigError(f"missing {key!r}")
    item_id = str(entry["id"]) if isinstance(entry["id"], int) and not isinstance(entry["id"], bool) else entry["id"]
    command = entry["command"]
    _check_command(command)
    options = entry.get("options", {})
    if not isinstance(options, dict):
        raise ConfigError(f"options: expected a JSON object, got {type(options).__name__}")
    parser = _command_parser(command)
    actions = _option_actions(parser)
    merged: dict[str, object] = {}
    for raw, value in [*((k, v) for k, v in entry.items() if k not in _ITEM_KEYS), *options.items()]:
        name = raw.replace("-", "_")
        if name in ("robot", "urdf"):
            if {"robot", "urdf"} & merged.keys():
                raise ConfigError("give the robot description once (robot or urdf)")
            name = robot_option(actions, name)
        if name in _RESERVED_OPTIONS:
            raise ConfigError(f"{raw}: the batch writes the outputs itself (OUT/<id>/{COMMANDS[command].result_file}, "
                              f"{COMMANDS[command].overlay_file}); leave out {', '.join(_RESERVED_OPTIONS)}")
        if name not in actions:
            raise ConfigError(f"unknown option {raw!r} for {command}; valid: {', '.join(sorted(actions))}")
        if name in merged:
            raise ConfigError(f"option {raw!r} is given twice")
        merged[name] = value
    base = Path(base)
    argv = tuple(word for name, value in merged.items() for word in _option_words(name, value, actions[name], base))
    parser.parse_args(argv)  # the command's own validation (required options, choices, types); UsageError
    return BatchItem(id=item_id, command=command, argv=argv, line=line)


def read_manifest(path: str | Path) -> list[BatchItem]:
    """All items of a JSON-lines manifest, every line checked before any work starts.

    Blank lines and lines starting with ``#`` are skipped. Raises ConfigError naming every bad line by its number
    (and duplicate ids), AssetError when the manifest itself is missing.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise AssetError(f"manifest not found: {path}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise AssetError(f"cannot read manifest {path}: {e}") from None
    items, problems, first_line = [], [], {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            try:
                entry = json.loads(line)
            except json.JSONDecodeError as e:
                raise ConfigError(f"not valid JSON ({e.msg} at column {e.colno})") from None
            item = item_from_dict(entry, path.parent, line=number)
            if item.id in first_line:
                raise ConfigError(f"id {item.id!r} is already used on line {first_line[item.id]}")
            first_line[item.id] = number
            items.append(item)
        except PipelineError as e:
            problems.append(f"line {number}: {' '.join(str(e).split())}")
    if problems:
        shown = "; ".join(problems[:10]) + (f"; and {len(problems) - 10} more" if len(problems) > 10 else "")
        raise ConfigError(f"{path}: {len(problems)} bad line(s): {shown}")
    if not items:
        raise ConfigError(f"{path}: no items (one JSON object per line)")
    return items


def parse_shard(text: str) -> tuple[int, int]:
    """``"i/N"`` -> ``(i, N)`` with ``0 <= i < N``."""
    index, sep, count = text.partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i, n = -1, 0
    if not sep or n < 1 or not 0 <= i < n:
        raise ConfigError(f"--shard: expected i/N with 0 <= i < N (e.g. 0/4 for the first of 4), got {text!r}")
    return i, n


def select_shard(items: Sequence[BatchItem], index: int, count: int) -> list[BatchItem]:
    """Every ``count``-th item starting at ``index`` (manifest order): shard ``index`` of ``count``."""
    if count < 1 or not 0 <= index < count:
        raise ConfigError(f"shard: expected 0 <= index < count, got {index}/{count}")
    return list(items[index::count])


# ---------------------------------------------------------------------------------------------------------------
# Worker side

_threads_set_to: int | None = None  # this process's thread count, once set
#: Robot models and segmenters this worker process has loaded (``pipeline.cli._args.loaded_once``), so that a
#: worker loads each once however many items use it; cleared when it holds more than ``_MODEL_CACHE_SIZE``.
_model_cache: dict = {}
_MODEL_CACHE_SIZE = 16


def configure_threads(threads: int) -> None:
    """Set this process's thread counts (torch, numba, OpenCV, OpenMP/BLAS; onnxruntime through each item's
    ``--onnx-threads``) to ``threads``; later calls with the same count do nothing."""
    global _threads_set_to
    if _threads_set_to == threads:
        return
    for variable in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[variable] = str(threads)  # read by the libraries this process has not started yet
    import cv2
    import numba
    import torch

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    cv2.setNumThreads(threads)
    _threads_set_to = threads


def run_cli_item(item: BatchItem, threads_per_task: int = 1) -> ItemResult:
    """Run one item in this process through its command's own parser and function; never raises for the item's
    own failure (the result says ``failed``). Output files come back as bytes in ``ItemResult.files``."""
    configure_threads(threads_per_task)
    from pipeline.cli import build_parser

    command = COMMANDS[item.command]
    start = time.perf_counter()
    printed = io.StringIO()
    with tempfile.TemporaryDirectory(prefix=f"batch-{item.id}-") as folder:
        result_path, overlay_path = Path(folder) / command.result_file, Path(folder) / command.overlay_file
        try:
            args = build_parser().parse_args([*command.argv, *item.argv, *command.extra_argv, "--out",
                                              str(result_path), command.overlay_option, str(overlay_path)])
            segments = any(getattr(args, name, None) is not None for name in ("image", "video", "frames"))
            if segments and getattr(args, "segmenter", None) in ("onnx", "auto") and args.onnx_threads is None:
                args.onnx_threads = threads_per_task
            if len(_model_cache) > _MODEL_CACHE_SIZE:
                _model_cache.clear()
            args.model_cache = _model_cache
            with contextlib.redirect_stdout(printed):
                args.func(args)
            files = {path.name: path.read_bytes() for path in (result_path, overlay_path) if path.exists()}
            if command.result_file not in files:
                raise PipelineError(f"{item.command} wrote no {command.result_file}")
            content = command.read(files[command.result_file])
            loss, figures = content.get("loss"), command.figures(content)
        except PipelineError as e:
            return ItemResult(id=item.id, command=item.command, status="failed",
                              seconds=time.perf_counter() - start, error=" ".join(str(e).split()) or type(e).__name__,
                              message=printed.getvalue())
        except Exception:  # a bug in one item must not stop the others; keep its traceback
            return ItemResult(id=item.id, command=item.command, status="failed",
                              seconds=time.perf_counter() - start, error=traceback.format_exc(),
                              message=printed.getvalue())
    return ItemResult(id=item.id, command=item.command, status="done", seconds=time.perf_counter() - start,
                      loss=loss, figures=figures, message=printed.getvalue(),
                      files=files)


def _run_item(item: BatchItem, threads_per_task: int) -> ItemResult:
    worker = COMMANDS[item.command].worker or run_cli_item
    return worker(item, threads_per_task)


# ---------------------------------------------------------------------------------------------------------------
# Driver side


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_item(result: ItemResult, out_dir: str | Path) -> ItemResult:
    """Write an item's files under ``out_dir/<id>/`` (temporary file + rename each; the result file last, as the
    item's "finished" mark), or its ``error.txt``; returns the result without the files' bytes."""
    folder = Path(out_dir) / result.id
    folder.mkdir(parents=True, exist_ok=True)
    if result.status == "done":
        result_file = COMMANDS[result.command].result_file
        for name, data in sorted(result.files.items(), key=lambda kv: kv[0] == result_file):
            _write_atomic(folder / name, data)
        (folder / ERROR_FILE).unlink(missing_ok=True)
    elif result.status == "failed":
        _write_atomic(folder / ERROR_FILE, (result.error or "").encode("utf-8"))
    return dataclasses.replace(result, files={})


def _finished_content(item: BatchItem, out_dir: str | Path) -> dict | None:
    """The item's result as its command reads it, or None when ``out_dir/<id>/`` holds no complete result."""
    command = COMMANDS[item.command]
    try:
        return command.read((Path(out_dir) / item.id / command.result_file).read_bytes())
    except (OSError, ValueError, KeyError, IndexError, TypeError, AttributeError):
        return None


def is_finished(item: BatchItem, out_dir: str | Path) -> bool:
    """Whether ``out_dir/<id>/`` holds the item's complete result (written last by ``write_item``; a track's
    JSONL with its summary line)."""
    return _finished_content(item, out_dir) is not None


def _skipped(item: BatchItem, out_dir: Path) -> ItemResult:
    content = _finished_content(item, out_dir) or {}
    try:
        loss, figures = content.get("loss"), COMMANDS[item.command].figures(content)
    except (ValueError, KeyError, IndexError, TypeError):
        loss, figures = None, {}
    return ItemResult(id=item.id, command=item.command, status="skipped", loss=loss, figures=figures)


def _worker_lost(item: BatchItem, error: Exception) -> ItemResult:
    return ItemResult(id=item.id, command=item.command, status="failed",
                      error=f"the worker running the item failed: {type(error).__name__}: {error}")


def _local_results(items: list[BatchItem], workers: int, threads: int) -> Iterator[ItemResult]:
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    limit = 2 * workers
    pending = list(reversed(items))
    with ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                             initializer=configure_threads, initargs=(threads,)) as pool:
        running: dict = {}  # future -> item
        while pending or running:
            while pending and len(running) < limit:
                item = pending.pop()
                running[pool.submit(_run_item, item, threads)] = item
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for future in finished:
                item = running.pop(future)
                try:
                    result = future.result()
                except Exception as e:  # the worker process died (killed, out of memory)
                    result = _worker_lost(item, e)
                yield result


def import_ray():
    """The ``ray`` module; ConfigError saying how to install it when it is missing."""
    try:
        import ray
    except ImportError as e:
        raise ConfigError(f"--engine ray needs Ray, which cannot be imported ({e}); install it with "
                          f"{RAY_INSTALL_HINT}") from None
    return ray


def _ray_results(items: list[BatchItem], threads: int, address: str | None) -> Iterator[ItemResult]:
    ray = import_ray()
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False, include_dashboard=False)
    elif address is not None:
        log.info("Ray is already initialised in this process; --address %s is not used", address)
    task = ray.remote(num_cpus=threads)(_run_item)
    limit = max(1, 2 * int(ray.cluster_resources().get("CPU", 1)) // threads)
    pending = list(reversed(items))
    running: dict = {}  # object ref -> item
    while pending or running:
        while pending and len(running) < limit:
            item = pending.pop()
            running[task.remote(item, threads)] = item
        finished, _ = ray.wait(list(running), num_returns=1)
        for ref in finished:
            item = running.pop(ref)
            try:
                result = ray.get(ref)
            except Exception as e:  # the task's worker or node died
                result = _worker_lost(item, e)
            yield result


def run(
    items: Iterable[BatchItem],
    out_dir: str | Path,
    *,
    engine: str = "local",
    workers: int = 1,
    threads_per_task: int = 1,
    resume: bool = False,
    address: str | None = None,
    progress: bool = True,
) -> Iterator[ItemResult]:
    """Run ``items``, yielding each ``ItemResult`` as it finishes (after its files are written under
    ``out_dir/<id>/``); skipped items (``resume`` and a result already there) come first.

    engine: ``local`` (a ``spawn`` process pool of ``workers`` processes) or ``ray`` (one Ray task per item
    needing ``threads_per_task`` CPUs, on the Ray already initialised in this process, else ``ray.init(address)``).
    Items go to the workers as paths and strings; each worker process loads its libraries once and sets its thread
    counts to ``threads_per_task``.
    """
    if engine not in ENGINES:
        raise ConfigError(f"engine: expected one of {', '.join(ENGINES)}, got {engine!r}")
    for name, value in (("workers", workers), ("threads_per_task", threads_per_task)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{name}: expected an integer >= 1, got {value!r}")
    items = list(items)
    if len({item.id for item in items}) != len(items):
        raise ConfigError("items: ids must be unique (each names its output folder)")
    if engine == "ray":
        import_ray()  # fail before any work
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    todo = [item for item in items if not (resume and is_finished(item, out_dir))]
    todo_ids = {item.id for item in todo}

    from tqdm import tqdm

    with tqdm(total=len(items), desc="batch", unit="item", disable=not progress) as bar:
        for item in items:
            if item.id not in todo_ids:
                bar.update()
                yield _skipped(item, out_dir)
        if not todo:
            return
        results = (_ray_results(todo, threads_per_task, address) if engine == "ray"
                   else _local_results(todo, min(workers, len(todo)), threads_per_task))
        for result in results:
            result = write_item(result, out_dir)
            if result.status == "failed":
                log.warning("item %s failed: %s", result.id, result.summary()["error"])
            bar.update()
            yield result


def write_summary(results: Sequence[ItemResult], path: str | Path) -> None:
    """``summary.jsonl``: one line per item (id, command, status, seconds, loss, key figures, error)."""
    text = "".join(json.dumps(r.summary()) + "\n" for r in results)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomic(path, text.encode("utf-8"))


def format_summary(results: Sequence[ItemResult], wall_seconds: float, *, max_failures: int = 10) -> str:
    """A one-screen text summary: counts, times, and the first failures."""
    counts = {status: sum(r.status == status for r in results) for status in STATUSES}
    ran = [r for r in results if r.status != "skipped"]
    item_seconds = sum(r.seconds for r in ran)
    lines = [f"{len(results)} items: {counts['done']} done, {counts['failed']} failed, {counts['skipped']} skipped "
             f"(finished earlier) in {wall_seconds:.1f} s wall"
             + (f"; {item_seconds / len(ran):.1f} s per item in the workers" if ran else "")]
    losses = [r.loss for r in results if r.loss is not None]
    if losses:
        lines.append(f"loss: median {sorted(losses)[len(losses) // 2]:.4g}, max {max(losses):.4g}")
    failed = [r for r in results if r.status == "failed"]
    for r in failed[:max_failures]:
        lines.append(f"  FAILED {r.id}: {r.summary()['error']}")
    if len(failed) > max_failures:
        lines.append(f"  ... and {len(failed) - max_failures} more failures (see summary.jsonl)")
    return "\n".join(lines)
