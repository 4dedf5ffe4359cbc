"""Is a shape-fit miss the search's fault or the loss's? The fit's loss against the loss at the truth, per arm.

For each arm (``benchmarks/shape_cases.py``, ``--kind``, seeds ``--seed``..): the default fit (automatic order,
or ``--order``) with its per-order losses and centreline errors; the loss of the true centreline written as a
Bezier curve of order ``--truth-order`` (least squares, ``_fit_bezier``; its own centreline error is printed, it
is the best that order can do); and a fit started from that curve (``--polish`` rendered iterations, no pre-fit,
one start: the local minimum next to the truth). When the fit ends above the truth's loss (or above the fit
started from the truth) the search missed a better minimum; when the truth scores no lower, the loss itself
cannot tell the true shape from the one found (e.g. the same silhouette from another 3D curve).

    python benchmarks/diagnose_shape_fit.py [--kind two_section] [--cases 20] [--seed 1000] [--truth-order 5]
        [--polish 200] [--from-truth-only] [--terms] [--set FIELD=VALUE ...] [--out diagnosis.json]

``--from-truth-only`` skips the default fit (the loss's own floor alone); ``--set`` overrides a ``ShapeFitConfig``
field of both fits (as in ``acceptance_shape.py``). ``dz mm`` is the fit from the truth's mean depth minus the
truth's: a loss whose minimum is not at the truth shows as a depth offset of one sign on every arm.

``--terms`` also splits the loss at the truth and at the default fit into its weighted terms (``mask``, ``keypoint``,
``length``: the same loss with the other weights set to 0) and names the kind of each miss over 2 px: ``keypoints``
when the truth's mask term is lower than the fit's (by > 0.002) and its keypoint term higher (by > 0.001): the
skeleton's keypoints, not the silhouette, pulled the fit off (e.g. an arm curling towards the camera, whose
skeleton path runs elsewhere than its projected centreline); ``search`` when the truth's loss is lower than the
fit's; else ``loss`` (the silhouette itself scores the wrong shape as well or better).

Only for tuning seeds (1000..); the acceptance benchmark reports 2000..2019.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time

import numpy as np
import torch
from acceptance_shape import parse_setting
from shape_cases import CAMERA, make_case, robot

from pipeline.evaluate import centerline_errors
from pipeline.shape_estimation import (ShapeFitConfig, _FitProblem, _fit_bezier, control_points_to_state,
                                       observe_mask, reconstruct_shape)
from pipeline.shapes.polyline import bezier_centerline, polyline_arc_length


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kind", default="two_section")
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--order", default="auto")
    parser.add_argument("--truth-order", type=int, default=5)
    parser.add_argument("--polish", type=int, default=200, help="iterations of the fit started from the truth")
    parser.add_argument("--from-truth-only", action="store_true", help="skip the default fit")
    parser.add_argument("--terms", action="store_true", help="split the losses at the truth and the fit into terms")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    parser.add_argument("--out")
    args = parser.parse_args()

    arm = robot()
    settings = dict(parse_setting(item) for item in args.set)
    settings.setdefault("model", "bezier")  # Bezier fits: their orders' curves, a polish from the truth's curve
    config = ShapeFitConfig(order=args.order if args.order == "auto" else int(args.order), **settings)
    rows = []
    print(f"{'seed':>5} {'order':>5} {'loss':>7} {'px':>6} {'mm':>6} | {'truth loss':>10} {'px':>5} {'mm':>5} | "
          f"{'from truth':>10} {'px':>5} {'mm':>5} {'dz mm':>6} | {'cpu s':>5}  per-order losses")
    for i in range(args.cases):
        case = make_case(args.seed + i, args.kind)
        cpu = time.process_time()
        if args.from_truth_only:
            result, e, per_order = None, {"mean_2d_px": math.nan, "mean_3d_mm": math.nan}, {}
        else:
            result = reconstruct_shape(case.mask, arm, CAMERA, config)
            e = centerline_errors(result.centerline_cam_m, case.truth_cam_m, CAMERA.K_array())
            per_order = {n: centerline_errors(bezier_centerline(c, 101), case.truth_cam_m, CAMERA.K_array())
                         for n, c in result.order_control_points.items()}
        cpu = time.process_time() - cpu
        frac = polyline_arc_length(case.truth_cam_m)
        truth = _fit_bezier(case.truth_cam_m, frac / frac[-1], args.truth_order)  # (n+1, 3)
        e_truth = centerline_errors(bezier_centerline(truth, 101), case.truth_cam_m, CAMERA.K_array())
        observation = observe_mask(case.mask, CAMERA, max_side=config.working_max_side,
                                   keypoints=config.keypoint_count,
                                   taper_ratio=arm.base_radius_m / arm.tip_radius_m)
        truth_terms = loss_terms(observation, arm, config, truth)
        truth_loss = truth_terms["total"]
        polished = reconstruct_shape(case.mask, arm, CAMERA, ShapeFitConfig(
            order=args.truth_order, iterations=args.polish, prefit_iterations=0, **settings),
            initial_control_points_cam_m=truth)
        e_pol = centerline_errors(polished.centerline_cam_m, case.truth_cam_m, CAMERA.K_array())
        dz_mm = 1000.0 * float(polished.centerline_cam_m[:, 2].mean() - case.truth_cam_m[:, 2].mean())
        order, loss = (result.order, result.loss) if result else (0, math.nan)
        row = {"seed": case.seed, "order": order, "loss": loss, "mean_2d_px": e["mean_2d_px"],
               "mean_3d_mm": e["mean_3d_mm"], "cpu_s": cpu, "order_losses": result.order_losses if result else {},
               "order_errors": {n: (v["mean_2d_px"], v["mean_3d_mm"]) for n, v in per_order.items()},
               "truth_loss": truth_loss, "truth_2d_px": e_truth["mean_2d_px"], "truth_3d_mm": e_truth["mean_3d_mm"],
               "from_truth_loss": polished.loss, "from_truth_2d_px": e_pol["mean_2d_px"],
               "from_truth_3d_mm": e_pol["mean_3d_mm"], "from_truth_dz_mm": dz_mm}
        if args.terms:
            row["truth_terms"] = truth_terms
            row["fit_terms"] = {} if result is None else loss_terms(observation, arm, config,
                                                                    np.asarray(result.control_points_cam_m))
            row["miss"] = miss_kind(row)
        rows.append(row)
        print(f"{case.seed:5d} {order:5d} {loss:7.4f} {e['mean_2d_px']:6.2f} {e['mean_3d_mm']:6.1f} | "
              f"{truth_loss:10.4f} {e_truth['mean_2d_px']:5.2f} {e_truth['mean_3d_mm']:5.1f} | "
              f"{polished.loss:10.4f} {e_pol['mean_2d_px']:5.2f} {e_pol['mean_3d_mm']:5.1f} {dz_mm:+6.1f} | {cpu:5.2f}  "
              + " ".join(f"{n}:{v:.4f}/{per_order[n]['mean_2d_px']:.1f}px" for n, v in row["order_losses"].items()),
              flush=True)
        if args.terms and result is not None:
            t, f = row["truth_terms"], row["fit_terms"]
            print(f"      terms mask / keypoint / length: truth {t['mask']:.4f} / {t['keypoint']:.4f} / "
                  f"{t['length']:.4f}, fit {f['mask']:.4f} / {f['keypoint']:.4f} / {f['length']:.4f}"
                  + (f" -> miss: {row['miss']}" if row["miss"] else ""), flush=True)
    print(f"\nmean: fit {statistics.mean(r['mean_2d_px'] for r in rows):.2f} px / "
          f"{statistics.mean(r['mean_3d_mm'] for r in rows):.2f} mm (loss {statistics.mean(r['loss'] for r in rows):.4f}); "
          f"from the truth {statistics.mean(r['from_truth_2d_px'] for r in rows):.2f} px / "
          f"{statistics.mean(r['from_truth_3d_mm'] for r in rows):.2f} mm "
          f"(loss {statistics.mean(r['from_truth_loss'] for r in rows):.4f}, depth offset "
          f"{statistics.mean(r['from_truth_dz_mm'] for r in rows):+.2f} mm); cpu "
          f"{statistics.mean(r['cpu_s'] for r in rows):.2f} s per fit")
    search = [r["seed"] for r in rows if r["from_truth_loss"] < r["loss"] - 0.002]
    print(f"fit ends above the fit from the truth (by > 0.002): {search}")
    if args.terms:
        kinds = {kind: [r["seed"] for r in rows if r.get("miss") == kind] for kind in ("keypoints", "search", "loss")}
        print("misses over 2 px by kind: " + ", ".join(f"{kind} {seeds}" for kind, seeds in kinds.items()))
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump(rows, f, indent=1, default=lambda v: v.tolist() if isinstance(v, np.ndarray) else str(v))


def loss_terms(observation, arm, config: ShapeFitConfig, control: np.ndarray) -> dict[str, float]:
    """The rendered fit's loss of the control points ``(n+1, 3)`` (radius offsets 0) and its weighted terms: the
    same loss with every other term's weight set to 0."""
    state = {"control": control_points_to_state(torch.from_numpy(np.asarray(control, dtype=np.float64))[None]).float(),
             "radius_offsets": torch.zeros(1, arm.n_rings)}
    weights = {"mask": "w_mask", "keypoint": "w_keypoint", "length": "w_length"}
    settings = {"total": config} | {
        term: dataclasses.replace(config, **{w: 0.0 for w in weights.values() if w != own})
        for term, own in weights.items()}
    with torch.no_grad():
        return {term: float(_FitProblem(observation, arm, c, torch.float32).loss(state, 0)[0])
                for term, c in settings.items()}


def miss_kind(row: dict) -> str | None:
    """``None`` for a fit within 2 px, else ``"keypoints"``, ``"search"`` or ``"loss"`` (module docstring)."""
    if not row["mean_2d_px"] > 2.0 or not row["fit_terms"]:
        return None
    t, f = row["truth_terms"], row["fit_terms"]
    if t["mask"] < f["mask"] - 0.002 and t["keypoint"] > f["keypoint"] + 0.001:
        return "keypoints"
    return "search" if t["total"] < f["total"] else "loss"


if __name__ == "__main__":
    main()
