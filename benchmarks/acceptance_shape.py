"""Acceptance round trip of the soft-arm shape fit on the project's own synthetic images.

20 random arms (``benchmarks/shape_cases.py``: 1280x720, fx 700, a 200 mm tapered arm 0.4 m away, drawn by
``synth.soft_arm``, masks by ``render_hard``), each fitted from its exact mask with the default ``ShapeFitConfig``
(``model="auto"`` since 2026-12-06: the Bezier fit, automatic order, mask + 4 keypoints, 200 iterations, 8 starts,
then its refinement as ``--sections`` constant-curvature sections, the lower loss kept; ``--model bezier`` for the
Bezier fit alone) or ``--order N``; the 2D (px) and 3D (mm)
centreline errors of ``pipeline.evaluate.centerline_errors`` per case, their mean and standard deviation, and
pass/fail against the targets. ``--kind quadratic`` (default): random quadratic Bezier arms, targets mean 2D < 2 px
and mean 3D < 5 mm (the paper on real data: 3.3 px, 6.9 mm). ``--kind two_section``: two 100 mm constant-curvature
sections, curvature 0-15 1/m each, free bending planes (S shapes included), random arm colours; targets (issue
13) < 2 px and < 4 mm; from RGB (``--source rgb``: the image segmented by ``--segmenter``, default ``auto``)
< 2.5 px and < 5 mm with no failed image, and the mask's IoU and area over the exact mask's are printed too (an
image whose segmentation or fit raises counts as failed). From RGB the fit reads the mask's rim offset from the
image (``rim_offset_px="image"``, as ``shape --image`` does; ``--set rim_offset_px=0`` for the mask as it is).
Seeds 2000..2019 were never used while tuning the defaults (those used 1000..1039; the
automatic order's penalty used 1000..1007 of both kinds).

    python benchmarks/acceptance_shape.py [--kind quadratic|two_section] [--order auto|N] [--cases 20]
        [--seed 2000] [--source mask|rgb] [--segmenter auto|onnx|color] [--model bezier|pcc|auto] [--sections 2] [--section-lengths L1,L2]
        [--set FIELD=VALUE ...] [--out results.json]

``--set`` overrides a ``ShapeFitConfig`` field (repeatable; ints and floats as such), for tuning on seeds other
than the reported ones. The process CPU time of each fit (``time.process_time``) is printed beside its wall time.

Exit code 0 when both targets are met, 1 otherwise.
"""

from __future__ import annotations

import argparse
from collections import Counter
import json
import statistics
import sys
import time

from shape_cases import CAMERA, make_case, robot

from pipeline.evaluate import centerline_errors
from pipeline.preprocess import clean_mask, join_pieces
from pipeline.shape_estimation import ShapeFitConfig, choose_arm_component, reconstruct_shape
from pipeline.shapes.polyline import bezier_centerline

#: (mean 2D px, mean 3D mm) targets per kind of arm, from exact masks.
TARGETS = {"quadratic": (2.0, 5.0), "two_section": (2.0, 4.0)}
#: The same from RGB (issue 13: < 2.5 px and < 5 mm on two-section arms).
RGB_TARGETS = {"quadratic": (2.0, 5.0), "two_section": (2.5, 5.0)}


def segmenter(kind: str, every_component: bool = False):
    """The segmenter of ``--segmenter``: ``auto`` (the default of ``shape --image``), ``onnx``, or ``color`` (the
    ``soft_arm`` preset, the default before issue 13); with ``every_component``, the same keeping every component
    (as ``shape --image`` segments: the fit keeps the component the arm's pre-fit explains best,
    ``choose_arm_component``, and joins the pieces of a cut arm)."""
    from pipeline.segment import AutoSegmenterConfig, OnnxSegmenterConfig, color_preset, make_segmenter

    largest = not every_component
    configs = {"auto": AutoSegmenterConfig(num_threads=1, largest_component=largest),
               "onnx": OnnxSegmenterConfig(num_threads=1, largest_component=largest),
               "color": color_preset("soft_arm", largest_component=largest)}
    return make_segmenter(configs[kind])


def segment_only(kind: str, seed: int, cases: int) -> int:
    """Per segmenter (auto, onnx, color): empty masks, mean and worst IoU, mean area over the exact mask's."""
    images = [make_case(seed + i, kind) for i in range(cases)]
    for name in ("auto", "onnx", "color"):
        segment = segmenter(name)
        ious, areas, empty = [], [], 0
        for case in images:
            mask = segment(case.image)
            empty += int(not mask.any())
            ious.append(float((mask & case.mask).sum() / max((mask | case.mask).sum(), 1)))
            areas.append(float(mask.sum() / case.mask.sum()))
        print(f"{name:>6}: {empty} empty of {cases}; IoU mean {statistics.mean(ious):.3f} (min {min(ious):.3f}); "
              f"area over the exact mask's mean {statistics.mean(areas):.3f} (min {min(areas):.3f}, "
              f"max {max(areas):.3f})", flush=True)
    return 0


def parse_setting(item: str) -> tuple[str, int | float | str]:
    """``"FIELD=VALUE"`` -> ``(FIELD, VALUE)``, the value an int, a float or else the string."""
    field, sep, text = item.partition("=")
    if not sep:
        raise SystemExit(f"--set: expected FIELD=VALUE, got {item!r}")
    for kind in (int, float):
        try:
            return field, kind(text)
        except ValueError:
            pass
    return field, text


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", type=int, default=20)
    parser.add_argument("--seed", type=int, default=2000, help="first seed (case i uses seed + i)")
    parser.add_argument("--kind", choices=sorted(TARGETS), default="quadratic", help="arms (default quadratic)")
    parser.add_argument("--order", default="auto", help="Bezier order of the fit, or auto (default)")
    parser.add_argument("--model", choices=("bezier", "pcc", "auto"), default="auto",
                        help="centreline model (default auto, the library's: the Bezier fit and its pcc refinement, "
                        "the lower loss kept; bezier; pcc: --sections constant-curvature sections)")
    parser.add_argument("--sections", type=int, default=2, help="with --model pcc or auto (default 2)")
    parser.add_argument("--section-lengths", help="with --model pcc or auto: L1,L2,... metres (default: fitted)")
    parser.add_argument("--source", choices=("mask", "rgb"), default="mask",
                        help="fit the exact mask (default) or the image segmented by --segmenter")
    parser.add_argument("--segmenter", choices=("auto", "onnx", "color"), default="auto",
                        help="with --source rgb (default auto)")
    parser.add_argument("--segment-only", action="store_true",
                        help="with --source rgb: only segment (no fit); print each segmenter's failures, IoU, area")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="override a ShapeFitConfig field (repeatable), e.g. --set order_starts=2")
    parser.add_argument("--out", help="write per-case results as JSON")
    args = parser.parse_args()
    if args.segment_only:
        return segment_only(args.kind, args.seed, args.cases)

    target_2d, target_3d = (TARGETS if args.source == "mask" else RGB_TARGETS)[args.kind]
    segment = segmenter(args.segmenter, every_component=True) if args.source == "rgb" else None
    settings = dict(parse_setting(item) for item in args.set)
    if segment is not None:  # as shape --image does: the rim read from the image unless --set says otherwise
        settings.setdefault("rim_offset_px", "image")
    config = ShapeFitConfig(order=args.order if args.order == "auto" else int(args.order), model=args.model,
                            sections=args.sections, section_lengths_m=tuple(
                                float(v) for v in args.section_lengths.split(",")) if args.section_lengths else (),
                            **settings)
    if args.set:
        print("settings: " + ", ".join(args.set))
    arm = robot()
    rows, failed = [], []
    print(f"{args.kind} arms, " + {"bezier": f"order {args.order}", "pcc": f"pcc, {args.sections} sections",
                                   "auto": f"auto: order {args.order} or pcc, {args.sections} sections"}[args.model]
          + ", from "
          + ("exact masks" if segment is None else f"RGB (segmenter {args.segmenter})"))
    print(f"{'case':>4} {'seed':>5} {'order':>5} {'2D px':>7} {'3D mm':>7} {'tip px':>7} {'len mm':>7} {'s':>6} "
          f"{'cpu s':>6} {'loss':>7}"
          + ("   IoU  area" if segment else ""))
    for i in range(args.cases):
        case = make_case(args.seed + i, args.kind)
        start, cpu = time.perf_counter(), time.process_time()
        mask, seg = case.mask, {}
        try:
            if segment is not None:  # as shape --image does: every component, the fit keeps the arm's
                mask = segment(case.image)
                if not mask.any():
                    seg.update({"iou": 0.0, "area_ratio": 0.0})
            result = reconstruct_shape(mask, arm, CAMERA, config, image=case.image if segment is not None else None)
        except (ValueError, RuntimeError) as e:  # a failed image (e.g. "mask is empty")
            failed.append({"seed": case.seed, "error": str(e), **seg})
            print(f"{i:4d} {case.seed:5d} FAILED: {e}", flush=True)
            continue
        seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
        if segment is not None:  # the arm's mask as the fit saw it: the chosen component, pieces joined (untimed)
            seen = clean_mask(join_pieces(choose_arm_component(mask, arm, CAMERA, config)[0]))
            seg.update({"arm_candidates": result.arm_candidates,
                        "iou": float((seen & case.mask).sum() / max((seen | case.mask).sum(), 1)),
                        "area_ratio": float(seen.sum() / case.mask.sum())})
        e = centerline_errors(result.centerline_cam_m, case.truth_cam_m, CAMERA.K_array())
        first = min(result.order_control_points)  # the first order's fit is the whole fit at that order alone
        e_first = e if result.model == "pcc" else centerline_errors(
            bezier_centerline(result.order_control_points[first], 101), case.truth_cam_m, CAMERA.K_array())
        rows.append({"seed": case.seed, **e, **seg, "rim_offset_px": result.rim_offset_px, "seconds": seconds,
                     "cpu_seconds": cpu, "loss": result.loss, "model": result.model,
                     "model_losses": result.model_losses, "order": result.order,
                     "order_losses": result.order_losses, "first_order": first,
                     "first_order_2d_px": e_first["mean_2d_px"], "first_order_3d_mm": e_first["mean_3d_mm"],
                     "base_end_disputed": result.base_end_disputed, "other_end_loss": result.other_end_loss})
        print(f"{i:4d} {case.seed:5d} {result.order:5d} {e['mean_2d_px']:7.2f} {e['mean_3d_mm']:7.2f} "
              f"{e['tip_2d_px']:7.2f} "
              f"{e['length_error_mm']:7.2f} {seconds:6.2f} {cpu:6.2f} {result.loss:7.4f}"
              + (f" {seg['iou']:6.3f} {seg['area_ratio']:5.3f}" if seg else ""), flush=True)
    e2 = [r["mean_2d_px"] for r in rows]
    e3 = [r["mean_3d_mm"] for r in rows]
    mean2, mean3 = statistics.mean(e2), statistics.mean(e3)
    std2 = statistics.stdev(e2) if len(e2) > 1 else 0.0
    std3 = statistics.stdev(e3) if len(e3) > 1 else 0.0
    passed = mean2 < target_2d and mean3 < target_3d and not failed
    print(f"\n{len(rows)} shapes: 2D {mean2:.2f} +- {std2:.2f} px (median {statistics.median(e2):.2f}), "
          f"3D {mean3:.2f} +- {std3:.2f} mm (median {statistics.median(e3):.2f}); "
          f"median {statistics.median(r['seconds'] for r in rows):.2f} s (cpu {statistics.median(r['cpu_seconds'] for r in rows):.2f} s, "
          f"mean {statistics.mean(r['cpu_seconds'] for r in rows):.2f} s) per shape; orders chosen (Bezier answers) "
          f"{dict(sorted(Counter(r['order'] for r in rows if r['model'] == 'bezier').items()))}")
    disputed = [r["seed"] for r in rows if r["base_end_disputed"]]
    print(f"base end disputed (border against widths; both ends fitted when fit_both_ends): {len(disputed)} "
          f"{disputed if disputed else ''}".rstrip())
    if args.model == "auto":
        print(f"models kept (the lower loss): {dict(sorted(Counter(r['model'] for r in rows).items()))}")
    first = rows[0]["first_order"]
    if args.model == "bezier":
        print(f"the same fits at order {first} (the first order of the search, identical to --order {first}): 2D "
              f"{statistics.mean(r['first_order_2d_px'] for r in rows):.2f} px, 3D "
              f"{statistics.mean(r['first_order_3d_mm'] for r in rows):.2f} mm")
    if segment is not None:
        ious, areas = [r["iou"] for r in rows], [r["area_ratio"] for r in rows]
        print(f"segmentation ({args.segmenter}): {len(failed)} failed of {args.cases}; mask IoU mean "
              f"{statistics.mean(ious):.3f} (min {min(ious):.3f}); area over the exact mask's mean "
              f"{statistics.mean(areas):.3f} (min {min(areas):.3f}, max {max(areas):.3f})")
    print(f"targets: 2D < {target_2d} px, 3D < {target_3d} mm" + (", no failed image" if segment else "")
          + f" -> {'PASS' if passed else 'FAIL'}")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as f:
            json.dump({"cases": rows, "failed": failed, "source": args.source,
                       "segmenter": args.segmenter if segment else None, "mean_2d_px": mean2, "std_2d_px": std2,
                       "mean_3d_mm": mean3, "std_3d_mm": std3, "passed": passed}, f, indent=1)
    return 0 if passed else 1


if __name__ == "__main__":
    sys.exit(main())
