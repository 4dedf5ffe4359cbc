"""Run a benchmark against an earlier commit, alternately in the same minutes, and print the ratio of a figure.

This machine's speed moves by a quarter from hour to hour (docs/tracking.md), so a speed-up is only measured
against the code before it run in the same minutes. This script checks the earlier commit out into a temporary
git worktree, runs the benchmark command there and in this checkout in turn (``--repeat`` rounds, this checkout
first), takes a figure from each run's output by a regular expression, and prints the medians and their ratio:

    python benchmarks/same_hour.py --against 12de6af --figure 'fit ([0-9.]+) s median' -- \\
        benchmarks/bench_track.py --frames 100 --single-every 1000 --seed 1 --segmenter file

The command runs with this interpreter, from each tree's root, with that tree first on ``PYTHONPATH``; the
environment (e.g. ``OMP_NUM_THREADS``) is passed on. The worktree is removed at the end. Each run's output lines
that match ``--show`` (default: the figure's) are printed as they come. A fresh worktree compiles the numba kernels
on its first run (their cache is per tree): take figures of warm frames or medians, not of a first fit.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(tree: Path, command: list[str], figure: re.Pattern, show: re.Pattern, label: str) -> float:
    """Run ``command`` in ``tree``; print its lines matching ``show``; return the figure's value."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tree), os.environ.get("PYTHONPATH", "")]).rstrip(
        os.pathsep))
    done = subprocess.run([sys.executable, *command], cwd=tree, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{label}: the command failed (exit {done.returncode}):\n{done.stderr[-2000:]}")
    found = None
    for line in done.stdout.splitlines():
        if show.search(line):
            print(f"  {label}: {line}")
        match = figure.search(line)
        if match and found is None:
            found = float(match.group(1))
    if found is None:
        raise SystemExit(f"{label}: no line of the output matches --figure {figure.pattern!r}")
    return found


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--against", required=True, metavar="COMMIT", help="the earlier commit")
    parser.add_argument("--figure", required=True, metavar="REGEX",
                        help="a regular expression whose first group is the figure (e.g. seconds)")
    parser.add_argument("--show", metavar="REGEX", help="print the output lines matching this (default: --figure)")
    parser.add_argument("--repeat", type=int, default=2, help="rounds of one run in each tree (default 2)")
    parser.add_argument("command", nargs="+", help="the benchmark script and its options (after --)")
    args = parser.parse_args()
    if args.repeat < 1:
        parser.error(f"--repeat: expected an int >= 1, got {args.repeat}")
    figure, show = re.compile(args.figure), re.compile(args.show or args.figure)
    values: dict[str, list[float]] = {"this checkout": [], args.against: []}
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "against"
        added = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "--quiet", str(tree),
                                args.against], capture_output=True, text=True)
        if added.returncode != 0:
            raise SystemExit(f"--against {args.against}: git could not check it out: {added.stderr.strip()}")
        try:
            for round_ in range(args.repeat):
                for label, where in (("this checkout", ROOT), (args.against, tree)):
                    values[label].append(run(where, args.command, figure, show, f"{label} (round {round_ + 1})"))
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False)
    ours, theirs = (statistics.median(v) for v in values.values())
    print(f"median figure: this checkout {ours:g}, {args.against} {theirs:g}; ratio {args.against} / this checkout "
          f"{theirs / ours:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
