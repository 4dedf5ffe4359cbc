"""Seconds per soft-arm shape reconstruction at 1280x720 input (default settings), and the split.

One synthetic arm (``benchmarks/shape_cases.py``, ``--kind``, default quadratic) reconstructed from its mask with
the default ``ShapeFitConfig`` (automatic order; ``--order N`` for one order), after one warm-up call (numba
kernels compiled or loaded from the disk cache); per run the wall time of ``reconstruct_shape`` and its split:
preprocessing (undistort, crop, shrink, clean, skeleton, widths, initial hypotheses, the soft-edge calibration),
pre-fit (skeleton and width, no rendering; of the first order's hypotheses and, with the automatic order, of every
further order's fresh ones) and the rendered fit (200 iterations, plus 160 per further order the automatic order
tries: 60 warm-up steps of its fresh starts and 100); also the process CPU time. Medians over
--runs. Torch and numba use their default thread counts unless --threads is given. Timings on a shared machine
vary with its load: the script prints the load average before and after.

    python benchmarks/bench_shape.py [--runs 5] [--threads N] [--seed 2000] [--kind quadratic] [--order auto]
        [--max-side PX] [--model bezier|pcc|auto] [--reference]

``--reference`` also times the rendered loss as tensor operations (``shape_estimation.FUSED_LOSS = False``, the
path before 2026-12-07), each run right after the default's on the same arm, and prints the ratio of the medians.

``--model`` sets the centreline model (default ``auto``, the library's: the Bezier fit, then its refinement as PCC
sections, ``pcc_iterations`` steps, the lower loss kept; ``bezier`` for the Bezier fit alone). ``--max-side`` sets the working side (default: the library's, 480); e.g. ``--max-side 320`` for the ratio
against the side before 2026-11-27 in the same conditions.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from shape_cases import CAMERA, make_case, robot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--threads", type=int, help="torch and numba threads (default: their defaults)")
    parser.add_argument("--seed", type=int, default=2000)
    parser.add_argument("--kind", default="quadratic", help="arm kind of shape_cases.py (default quadratic)")
    parser.add_argument("--order", default="auto", help="Bezier order of the fit, or auto (default)")
    parser.add_argument("--max-side", type=int, help="working side of the fit (default: the library's)")
    parser.add_argument("--model", choices=("bezier", "pcc", "auto"), default="auto",
                        help="centreline model (default auto, the library's)")
    parser.add_argument("--reference", action="store_true",
                        help="also time the rendered loss as tensor operations, and print the ratio")
    args = parser.parse_args()

    import numba
    import torch

    from pipeline import shape_estimation
    from pipeline.shape_estimation import ShapeFitConfig, reconstruct_shape

    if args.threads is not None:
        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)
    case = make_case(args.seed, args.kind)
    side = {} if args.max_side is None else {"working_max_side": args.max_side}
    arm, config = robot(), ShapeFitConfig(order=args.order if args.order == "auto" else int(args.order),
                                          model=args.model, **side)
    warm_up = ShapeFitConfig(iterations=2, prefit_iterations=2, order_iterations=2)
    reconstruct_shape(case.mask, arm, CAMERA, warm_up)  # numba kernels compiled or loaded
    print(f"{CAMERA.width}x{CAMERA.height} input, {config.iterations} iterations, {config.starts} starts, "
          f"working side {config.working_max_side}; torch threads {torch.get_num_threads()}, numba threads "
          f"{numba.get_num_threads()}; load average {os.getloadavg()[0]:.2f}")
    paths = (True, False) if args.reference else (True,)
    rows = {fused: [] for fused in paths}
    for run in range(args.runs):
        for fused in paths:
            shape_estimation.FUSED_LOSS = fused
            cpu, wall = time.process_time(), time.perf_counter()
            result = reconstruct_shape(case.mask, arm, CAMERA, config)
            rows[fused].append((time.perf_counter() - wall, result.preprocess_seconds, result.prefit_seconds,
                                result.fit_seconds, time.process_time() - cpu))
            row = rows[fused][-1]
            print(f"run {run}{'' if fused else ' (tensor loss)'}: {row[0]:.2f} s (preprocess {row[1]:.2f}, pre-fit "
                  f"{row[2]:.2f}, fit {row[3]:.2f}; cpu {row[4]:.2f} s)", flush=True)
    shape_estimation.FUSED_LOSS = True
    medians = {fused: [statistics.median(column) for column in zip(*rows[fused])] for fused in paths}
    for fused, median in medians.items():
        print(f"median of {args.runs}{'' if fused else ' (tensor loss)'}: {median[0]:.2f} s per reconstruction: "
              f"preprocess {median[1]:.2f} s, pre-fit {median[2]:.2f} s, fit {median[3]:.2f} s (model {result.model}, "
              f"order {result.order}, {result.iterations} iterations, "
              f"{1000 * median[3] / result.iterations:.1f} ms per iteration); cpu {median[4]:.2f} s; "
              f"load average now {os.getloadavg()[0]:.2f}")
    median = medians[True]
    if args.reference:
        print(f"the tensor loss over the compiled one: {medians[False][0] / median[0]:.2f}x the wall time, "
              f"{medians[False][4] / median[4]:.2f}x the CPU time")
    print(f"target < 5 s: {'PASS' if median[0] < 5.0 else 'FAIL'}")


if __name__ == "__main__":
    main()
