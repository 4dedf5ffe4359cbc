"""Replay a per-arm choice between two runs of ``acceptance_shape.py`` on the same arms, from their ``--out`` files.

For each arm the result of run B replaces run A's where B ends lower: by ``loss`` (the default; e.g. A the
Bezier fit, B ``--model pcc``), or by the auto order's score, ``loss + order_penalty * (order - 2)`` (``--score``;
e.g. two hypothesis seeds). ``--gates`` also replays the choice made only where A's loss is above each gate (a
second fit spent on high losses only). Prints the mean 2D px / 3D mm (medians in brackets) of A, B and each choice.

    python benchmarks/replay_choice.py bezier.json pcc_1000.json,pcc_1030.json
    python benchmarks/replay_choice.py seed0.json seed1.json --score --gates 0.03,0.035,0.04

docs/soft-arms.md uses it (the sections of 2026-12-06).
"""

from __future__ import annotations

import argparse
import json
import statistics


def load(paths: str) -> dict[int, dict]:
    """The cases of one or more comma-separated ``--out`` files, by seed."""
    cases = {}
    for path in paths.split(","):
        with open(path, encoding="utf-8") as f:
            cases.update({row["seed"]: row for row in json.load(f)["cases"]})
    return cases


def summary(rows: list[dict]) -> str:
    px = [r["mean_2d_px"] for r in rows]
    mm = [r["mean_3d_mm"] for r in rows]
    return (f"{statistics.fmean(px):.2f} / {statistics.fmean(mm):.2f} "
            f"({statistics.median(px):.2f} / {statistics.median(mm):.2f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("a", help="acceptance_shape.py --out file(s) of run A, comma-separated (kept unless B is lower)")
    parser.add_argument("b", help="the same of run B, on the same arms")
    parser.add_argument("--score", action="store_true", help="compare loss + order_penalty * (order - 2)")
    parser.add_argument("--order-penalty", type=float, default=0.002)
    parser.add_argument("--gates", default="", help="comma-separated losses of A above which B is tried")
    args = parser.parse_args()
    a, b = load(args.a), load(args.b)
    seeds = sorted(set(a) & set(b))
    if not seeds:
        raise SystemExit("the two files share no arm (their seeds differ)")

    def value(row: dict) -> float:
        return row["loss"] + (args.order_penalty * (row["order"] - 2) if args.score else 0.0)

    def choice(gate: float | None) -> tuple[list[dict], int]:
        tried = [s for s in seeds if gate is None or a[s]["loss"] > gate]
        rows = [b[s] if s in tried and value(b[s]) < value(a[s]) else a[s] for s in seeds]
        return rows, len(tried)

    print(f"{len(seeds)} arms; mean 2D px / 3D mm (median); compared by {'score' if args.score else 'loss'}")
    print(f"A: {summary([a[s] for s in seeds])}")
    print(f"B: {summary([b[s] for s in seeds])}")
    rows, _ = choice(None)
    print(f"the lower of A and B: {summary(rows)}; B kept on {sum(r is b[r['seed']] for r in rows)}")
    for gate in (float(g) for g in args.gates.split(",") if g):
        rows, tried = choice(gate)
        print(f"B tried where A's loss > {gate:g} ({tried} arms): {summary(rows)}")


if __name__ == "__main__":
    main()
