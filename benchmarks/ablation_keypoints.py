"""Ablation in the layout of the paper's Table I, on synthetic arms: which loss, and which Bezier order.

Table 1 (loss variants): random quadratic arms (``benchmarks/shape_cases.py``, 1280x720, fx 700, 200 mm at
0.4 m) fitted with a quadratic centreline and the loss of each ``keypoint_mode``: the mask only, mask + the tip
(endpoint), mask + 4 keypoints. Everything else is the default ``ShapeFitConfig``; in particular the
initialisation and the pre-fit use the mask's skeleton in every variant (the variants differ in the rendered
fit's loss), and one more row, ``mask only, no pre-fit``, shows what the skeleton pre-fit adds.
Table 2 (curve order): arms that are not quadratics (two constant-curvature arcs, "pcc"; cubic S shapes) fitted
with order 2 and order 3, mask + 4 keypoints.

Cells are the mean +- standard deviation over the cases of ``centerline_errors``' mean 2D error (px) and mean
3D error (mm). Prints markdown tables.

    python benchmarks/ablation_keypoints.py [--cases 10] [--order-cases 8] [--seed 3000]
"""

from __future__ import annotations

import argparse
import statistics
import time

from shape_cases import CAMERA, make_case, robot

from pipeline.evaluate import centerline_errors
from pipeline.shape_estimation import ShapeFitConfig, reconstruct_shape


def run(cases, config: ShapeFitConfig) -> tuple[list[float], list[float]]:
    e2, e3 = [], []
    for case in cases:
        result = reconstruct_shape(case.mask, robot(), CAMERA, config)
        e = centerline_errors(result.centerline_cam_m, case.truth_cam_m, CAMERA.K_array())
        e2.append(e["mean_2d_px"])
        e3.append(e["mean_3d_mm"])
    return e2, e3


def cell(values: list[float]) -> str:
    std = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{statistics.mean(values):.2f} +- {std:.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=10, help="quadratic arms for the loss table")
    parser.add_argument("--order-cases", type=int, default=8, help="arms of each kind for the order table")
    parser.add_argument("--seed", type=int, default=3000)
    args = parser.parse_args()
    start = time.perf_counter()

    quadratic = [make_case(args.seed + i, "quadratic") for i in range(args.cases)]
    print(f"Table 1: loss variants, {len(quadratic)} random quadratic arms, quadratic fit\n")
    print("| loss | 2D error (px) | 3D error (mm) |\n|---|---|---|")
    variants = [
        ("mask only", ShapeFitConfig(model="bezier", order=2, keypoint_mode="mask")),
        ("mask + endpoint", ShapeFitConfig(model="bezier", order=2, keypoint_mode="endpoint")),
        ("mask + 4 keypoints", ShapeFitConfig(model="bezier", order=2, keypoint_mode="keypoints", keypoints=4)),
        ("mask only, no pre-fit", ShapeFitConfig(model="bezier", order=2, keypoint_mode="mask", prefit_iterations=0)),
    ]
    for name, config in variants:
        e2, e3 = run(quadratic, config)
        print(f"| {name} | {cell(e2)} | {cell(e3)} |", flush=True)

    print(f"\nTable 2: Bezier order, {args.order_cases} arms of each kind, mask + 4 keypoints\n")
    print("| arms | order 2: 2D (px) | order 2: 3D (mm) | order 3: 2D (px) | order 3: 3D (mm) |\n|---|---|---|---|---|")
    for kind, seed in (("pcc", args.seed + 100), ("cubic_s", args.seed + 200)):
        cases = [make_case(seed + i, kind) for i in range(args.order_cases)]
        row = [kind]
        for order in (2, 3):
            e2, e3 = run(cases, ShapeFitConfig(model="bezier", order=order))
            row += [cell(e2), cell(e3)]
        print("| " + " | ".join(row) + " |", flush=True)
    print(f"\n{time.perf_counter() - start:.0f} s in all")


if __name__ == "__main__":
    main()
