"""How ``ShapeFitConfig.order_penalty`` was chosen: per-order losses and errors on tuning arms, then each penalty.

Fits ``--cases`` arms of each kind (``quadratic``: single bends; ``two_section``: two constant-curvature sections,
0-15 1/m, free bending planes) from their exact masks with ``order="auto"`` and no penalty (so every order 2..5
is fitted while its loss goes down), and keeps each order's loss and centreline error. Then, for each candidate
penalty, replays the automatic choice (lowest ``loss + penalty * (n - 2)``, stopping at the first order that does
not lower it; and, marked "no stop", the lowest score of all orders fitted) and prints the mean errors and the
orders chosen. The seeds (1000.. by default) are not those the
acceptance benchmark reports (2000..).

    python benchmarks/tune_order_penalty.py [--cases 8] [--seed 1000] [--out tuning.json]
"""

from __future__ import annotations

import argparse
import json
import statistics

from shape_cases import CAMERA, make_case, robot

from pipeline.evaluate import centerline_errors
from pipeline.shape_estimation import ShapeFitConfig, reconstruct_shape
from pipeline.shapes.polyline import bezier_centerline

PENALTIES = (0.0, 0.001, 0.002, 0.003, 0.004, 0.005, 0.01)


def choose(losses: dict[int, float], penalty: float, stop: bool = True) -> int:
    """The order ``ShapeFitConfig(order="auto", order_penalty=penalty)`` keeps, given every order's loss; with
    ``stop=False`` the lowest score of all orders (as if the search went on past an order that did not pay)."""
    chosen = min(losses)
    for order in sorted(losses)[1:]:
        if losses[order] + penalty * (order - 2) >= losses[chosen] + penalty * (chosen - 2):
            if stop:
                break
            continue
        chosen = order
    return chosen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=8)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--out", help="write the per-order losses and errors as JSON")
    args = parser.parse_args()

    rows = []
    for kind in ("quadratic", "two_section"):
        for i in range(args.cases):
            case = make_case(args.seed + i, kind)
            result = reconstruct_shape(case.mask, robot(), CAMERA, ShapeFitConfig(model="bezier", order_penalty=0.0))
            errors = {}
            for order, control in result.order_control_points.items():
                e = centerline_errors(bezier_centerline(control, 101), case.truth_cam_m, CAMERA.K_array())
                errors[order] = (e["mean_2d_px"], e["mean_3d_mm"])
            rows.append({"kind": kind, "seed": case.seed, "losses": result.order_losses, "errors": errors})
            print(kind, case.seed, {n: f"{v:.4f}" for n, v in result.order_losses.items()},
                  {n: f"{a:.2f} px / {b:.1f} mm" for n, (a, b) in errors.items()}, flush=True)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump(rows, f, indent=1)
    print("\n| penalty | quadratic: px / mm | orders | two_section: px / mm | orders |\n|---|---|---|---|---|")
    for penalty, stop in [(p, True) for p in PENALTIES] + [(p, False) for p in PENALTIES]:
        cells = []
        for kind in ("quadratic", "two_section"):
            picked = [(r, choose(r["losses"], penalty, stop)) for r in rows if r["kind"] == kind]
            if not picked:
                cells += ["-", "-"]
                continue
            px = statistics.mean(r["errors"][n][0] for r, n in picked)
            mm = statistics.mean(r["errors"][n][1] for r, n in picked)
            cells += [f"{px:.2f} / {mm:.2f}", " ".join(str(n) for _, n in picked)]
        print(f"| {penalty}{'' if stop else ' (no stop)'} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
