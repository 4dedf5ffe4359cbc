"""Batch runs: ``pipeline batch --engine local --workers 2`` and ``--engine ray`` against a serial loop over the CLI.

16 pose items (data/toy_arm, seeds 0..15) and 16 shape items (data/soft_arm/quadratic, seeds 0..15), with small
iteration counts so the whole benchmark takes a few minutes. Each way runs as a fresh process (the CLI loop pays
Python start-up and model loading per item, the engines once per worker). Prints wall times, the ratio to the CLI
loop, and the overhead per item: (wall x processes working - the fits' own seconds from result.json) / items, and
checks that every way gives the same losses.

    PYTHONPATH=$PWD python benchmarks/bench_batch.py [--items 16] [--skip-ray]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOY = REPO / "data" / "toy_arm"
ARM = REPO / "data" / "soft_arm" / "quadratic"
URDF = REPO / "models" / "robots" / "toy_arm_mesh" / "toy_arm_mesh.urdf"


def manifest_entries(n: int) -> list[dict]:
    joints = json.loads((TOY / "joints.json").read_text())
    pose = [{"id": f"pose-{i:02d}", "command": "pose", "camera": str(TOY / "camera.json"),
             "mask": str(TOY / "mask.png"), "robot": str(URDF), "root": "base_link", "joints": joints,
             "options": {"iterations": 40, "starts": 4, "working_max_side": 160, "polish_rounds": 5,
                         "polish_newton_steps": 3, "retries": 0, "seed": i}} for i in range(n)]
    shape = [{"id": f"shape-{i:02d}", "command": "shape", "camera": str(ARM / "camera.json"),
              "mask": str(ARM / "mask.png"), "length": 0.2, "base_radius": 0.014, "tip_radius": 0.006,
              "options": {"iterations": 40, "starts": 2, "seed": i}} for i in range(n)]
    return pose + shape


def fit_seconds(out_dir: Path, ids: list[str]) -> tuple[float, dict[str, float]]:
    total, losses = 0.0, {}
    for item_id in ids:
        result = json.loads((out_dir / item_id / "result.json").read_text())
        total += result["seconds"]
        losses[item_id] = result["loss"]
    return total, losses


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=16, help="items of each command (default 16)")
    parser.add_argument("--skip-ray", action="store_true")
    args = parser.parse_args()

    from pipeline import batch

    folder = Path(tempfile.mkdtemp(prefix="bench_batch_"))
    entries = manifest_entries(args.items)
    manifest = folder / "manifest.jsonl"
    manifest.write_text("".join(json.dumps(e) + "\n" for e in entries))
    items = batch.read_manifest(manifest)
    ids = [item.id for item in items]
    python = [sys.executable, "-m", "pipeline"]

    rows = []
    out = folder / "cli"
    start = time.perf_counter()
    for item in items:
        (out / item.id).mkdir(parents=True)
        subprocess.run([*python, item.command, *item.argv, "--out", str(out / item.id / "result.json"),
                        "--overlay", str(out / item.id / "overlay.png")], check=True, capture_output=True)
    rows.append(("serial CLI loop", time.perf_counter() - start, 1, out))

    ways = [("local, 2 workers", ["--engine", "local", "--workers", "2"], 2)]
    if not args.skip_ray:
        ways.append(("ray (2 CPUs)", ["--engine", "ray"], 2))
    for name, options, processes in ways:
        out = folder / name.split()[0].strip(",")
        start = time.perf_counter()
        subprocess.run([*python, "batch", str(manifest), "--out", str(out), "--no-progress", *options], check=True,
                       capture_output=True)
        rows.append((name, time.perf_counter() - start, processes, out))

    reference_losses = fit_seconds(rows[0][3], ids)[1]
    print(f"{len(items)} items ({args.items} pose + {args.items} shape), outputs in {folder}")
    print(f"{'way':<18} {'wall s':>8} {'vs CLI loop':>12} {'fits s':>8} {'overhead s/item':>16}  same losses")
    for name, wall, processes, out in rows:
        fits, losses = fit_seconds(out, ids)
        overhead = (wall * processes - fits) / len(items)
        print(f"{name:<18} {wall:8.1f} {rows[0][1] / wall:11.2f}x {fits:8.1f} {overhead:16.2f}  "
              f"{losses == reference_losses}")


if __name__ == "__main__":
    main()
