"""``pipeline batch``: run many ``pose`` / ``shape`` / ``track shape`` / ``track pose`` items from a JSON-lines
manifest (local process pool or Ray)."""

from __future__ import annotations

import argparse


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "batch",
        help="run many pose/shape/track items from a JSON-lines manifest, in local processes or on Ray",
        description="Run every item of MANIFEST.jsonl (one JSON object per line in the single commands' "
        "vocabulary: id, command, camera, mask or image or frames or video, robot/urdf, root, joints, ..., options) "
        "and write OUT/<id>/result.json and overlay.png (result.jsonl and overlay.mp4 for track shape and track "
        "pose; error.txt when an item fails) and OUT/summary.jsonl. Relative paths "
        "resolve against the manifest's folder; every line is checked before any work starts. Exit code 0 when "
        "every item succeeded, 1 when some failed, 2 on bad input.",
    )
    parser.add_argument("manifest", metavar="MANIFEST.jsonl", help="one item per line")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder (OUT/<id>/, OUT/summary.jsonl)")
    parser.add_argument(
        "--engine", choices=("local", "ray"), default="local",
        help="local: a process pool on this machine (default); ray: Ray tasks (pip install '.[ray]')",
    )  # fmt: skip
    parser.add_argument(
        "--address", metavar="ADDR",
        help="ray: the cluster to join ('auto': the one started on this node with 'ray start'; default: a new "
        "local Ray)",
    )  # fmt: skip
    parser.add_argument(
        "--workers", type=int, metavar="N",
        help="local: worker processes (default: CPU cores / --threads-per-task)",
    )  # fmt: skip
    parser.add_argument(
        "--threads-per-task", type=int, default=1, metavar="N",
        help="threads of each item (torch, numba, OpenCV, onnxruntime) and its Ray CPUs (default 1)",
    )  # fmt: skip
    parser.add_argument("--shard", metavar="i/N", help="run only every N-th item starting at i (0 <= i < N)")
    parser.add_argument("--resume", action="store_true", help="skip items whose OUT/<id>/result.json(l) is complete")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import os
    import time
    from pathlib import Path

    from pipeline import batch
    from pipeline.errors import ConfigError

    if args.threads_per_task < 1:
        raise ConfigError(f"--threads-per-task: expected an integer >= 1, got {args.threads_per_task}")
    if args.workers is not None and args.workers < 1:
        raise ConfigError(f"--workers: expected an integer >= 1, got {args.workers}")
    if args.engine != "ray" and args.address is not None:
        raise ConfigError("--address: only with --engine ray")
    if args.engine == "ray":
        batch.import_ray()  # a missing Ray fails before the manifest is read
    workers = args.workers or max(1, (os.cpu_count() or 1) // args.threads_per_task)
    items = batch.read_manifest(args.manifest)
    summary_name = "summary.jsonl"
    if args.shard is not None:
        index, count = batch.parse_shard(args.shard)
        items = batch.select_shard(items, index, count)
        summary_name = f"summary-shard-{index}-of-{count}.jsonl"
    start = time.perf_counter()
    results = list(batch.run(items, args.out, engine=args.engine, workers=workers,
                             threads_per_task=args.threads_per_task, resume=args.resume, address=args.address,
                             progress=not args.no_progress))
    order = {item.id: n for n, item in enumerate(items)}
    results.sort(key=lambda r: order[r.id])
    summary = Path(args.out) / summary_name
    batch.write_summary(results, summary)
    print(batch.format_summary(results, time.perf_counter() - start))
    print(f"summary: {summary}")
    return 1 if any(r.status == "failed" for r in results) else 0
