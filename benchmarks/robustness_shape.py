"""Robustness of the soft-arm shape fit to what real masks get wrong (issue 13, point 4).

The arms of ``benchmarks/shape_cases.py`` (``--kind``, default quadratic), each fitted with the default
``ShapeFitConfig`` from its exact mask and from the mask spoilt in one way at a time; the mean 2D (px) and 3D (mm)
centreline errors per condition:

- ``exact``: the exact mask (the baseline);
- ``rim+1``, ``rim+2``, ``rim-1``, ``rim-2``: the rim moved out / in by 1 or 2 px (dilated / eroded by a disk);
- ``occluded``: a band across the arm hidden at the middle of its skeleton (a bar as wide as the arm's
  apparent diameter there, perpendicular to the arm) - the mask falls in two pieces;
- ``blob``: a false-positive disk (radius one arm diameter) touching the arm's side at the middle of its
  skeleton;
- ``blur``: the image motion-blurred (a 15 px line kernel in a random direction) and segmented by the default
  segmenter (``auto``);
- ``occluded-rgb``: the ``occluded`` bar drawn grey in front of the arm in the image, which is then segmented as
  ``shape --image`` does (``auto``, every component kept; the fit keeps the arm's).

    python benchmarks/robustness_shape.py [--kind quadratic] [--cases 5] [--seed 2000] [--only COND,...]
        [--known-rim | --auto-rim | --image-rim] [--model auto|bezier|pcc]

``--auto-rim``: every fit searches the rim offset itself (``rim_offset_px="auto"``), exact masks included.
``--image-rim``: every fit reads it from the image the mask goes with (``rim_offset_px="image"``, as ``shape
--image`` does by default; the blurred or occluded image for ``blur`` and ``occluded-rgb``). Without it the
``blur`` and ``occluded-rgb`` masks are fitted as they are (as ``shape --image --rim-offset-px 0``).
``--known-rim``: the rim conditions' fits are told the rim offset (``ShapeFitConfig.rim_offset_px``), measured as a
user would on frames with true masks (``pipeline.evaluate.rim_offset_px`` of the spoilt mask against the exact
one); the other conditions are fitted as without it.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace

import cv2
import numpy as np
from shape_cases import CAMERA, make_case, robot

from pipeline.evaluate import centerline_errors, rim_offset_px
from pipeline.preprocess import exact_distance_transform, skeleton_path
from pipeline.shape_estimation import ShapeFitConfig, reconstruct_shape

CONDITIONS = ("exact", "rim+1", "rim+2", "rim-1", "rim-2", "occluded", "blob", "blur", "occluded-rgb")


def _disk(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _middle(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The skeleton path's middle point ``(u, v)``, the unit normal there, and the mask's half-width there."""
    path = skeleton_path(mask, (0.0, 0.0))
    i = len(path) // 2
    tangent = path[min(i + 3, len(path) - 1)] - path[max(i - 3, 0)]
    tangent = tangent / max(np.linalg.norm(tangent), 1e-9)
    half = float(exact_distance_transform(mask)[int(round(path[i, 1])), int(round(path[i, 0]))])
    return path[i], np.array([-tangent[1], tangent[0]]), half


def spoil(condition: str, mask: np.ndarray, image: np.ndarray, rng: np.random.Generator, segmenter,
          every_segmenter=None) -> tuple[np.ndarray, np.ndarray]:
    """The mask of ``condition`` (see the module docstring), ``(H, W)`` bool, and the image it goes with (the
    blurred or occluded image the segmenter saw; ``image`` itself for the conditions made on the mask)."""
    mask, seen = _spoil(condition, mask, image, rng, segmenter, every_segmenter)
    return mask, image if seen is None else seen


def _spoil(condition, mask, image, rng, segmenter, every_segmenter):
    if condition == "exact":
        return mask, None
    if condition.startswith("rim"):
        step = int(condition[-1])
        operation = cv2.dilate if condition[3] == "+" else cv2.erode
        return operation(mask.astype(np.uint8), _disk(step)) > 0, None
    if condition == "blur":
        angle = rng.uniform(0.0, np.pi)
        kernel = np.zeros((15, 15), np.float32)
        c, s = 7 * np.cos(angle), 7 * np.sin(angle)
        cv2.line(kernel, (int(round(7 - c)), int(round(7 - s))), (int(round(7 + c)), int(round(7 + s))), 1.0, 1)
        blurred = cv2.filter2D(image, -1, kernel / kernel.sum())
        return segmenter(blurred), blurred
    centre, normal, half = _middle(mask)
    out = mask.copy()
    if condition in ("occluded", "occluded-rgb"):
        tangent = np.array([normal[1], -normal[0]])
        a, b = centre - 3 * half * normal, centre + 3 * half * normal
        corners = np.array([a - half * tangent, b - half * tangent, b + half * tangent, a + half * tangent])
        bar = np.zeros(mask.shape, np.uint8)
        cv2.fillConvexPoly(bar, np.round(corners).astype(np.int32), 1)
        if condition == "occluded":
            return out & (bar == 0), None
        hidden = image.copy()
        hidden[bar > 0] = np.clip(128 + rng.normal(0.0, 3.0, (int(bar.sum()), 3)), 0, 255).astype(np.uint8)
        return every_segmenter(hidden), hidden
    if condition == "blob":
        radius = 2.0 * half
        u, v = centre + normal * (half + radius - 1.0)
        blob = np.zeros(mask.shape, np.uint8)
        cv2.circle(blob, (int(round(u)), int(round(v))), int(round(radius)), 1, -1)
        return out | (blob > 0), None
    raise ValueError(f"condition: expected one of {', '.join(CONDITIONS)}, got {condition!r}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--kind", default="quadratic")
    parser.add_argument("--cases", type=int, default=5)
    parser.add_argument("--seed", type=int, default=2000)
    parser.add_argument("--only", help="comma-separated conditions (default all)")
    parser.add_argument("--model", choices=("bezier", "pcc", "auto"), default="auto",
                        help="centreline model (default auto, the library's)")
    parser.add_argument("--known-rim", action="store_true", help="tell the rim conditions' fits their rim offset")
    parser.add_argument("--auto-rim", action="store_true", help="every fit searches the rim offset (rim_offset_px='auto')")
    parser.add_argument("--image-rim", action="store_true",
                        help="every fit reads the rim offset from the image (rim_offset_px='image', as shape --image)")
    args = parser.parse_args()
    conditions = args.only.split(",") if args.only else list(CONDITIONS)
    from pipeline.segment import AutoSegmenterConfig, make_segmenter

    segmenter = make_segmenter(AutoSegmenterConfig(num_threads=1))
    every_segmenter = make_segmenter(AutoSegmenterConfig(num_threads=1, largest_component=False))
    arm, config = robot(), ShapeFitConfig(model=args.model)
    cases = [make_case(args.seed + i, args.kind) for i in range(args.cases)]
    print(f"{args.kind} arms, seeds {args.seed}..{args.seed + args.cases - 1}, default settings"
          + (", rim conditions told their rim offset" if args.known_rim else "")
          + (", rim offset searched (rim_offset_px='auto')" if args.auto_rim else "")
          + (", rim offset read from the image (rim_offset_px='image')" if args.image_rim else ""))
    print(f"{'condition':>10} {'2D px':>7} {'3D mm':>7}  per arm (2D px / 3D mm)")
    for condition in conditions:
        rows = []
        for case in cases:
            rng = np.random.default_rng(case.seed)
            mask, image = spoil(condition, case.mask, case.image, rng, segmenter, every_segmenter)
            start = time.perf_counter()
            rim = rim_offset_px(mask, case.mask) if args.known_rim and condition.startswith("rim") else 0.0
            rim = "auto" if args.auto_rim else "image" if args.image_rim else rim
            result = reconstruct_shape(mask, arm, CAMERA, replace(config, rim_offset_px=rim), image=image)
            e = centerline_errors(result.centerline_cam_m, case.truth_cam_m, CAMERA.K_array())
            rows.append((e["mean_2d_px"], e["mean_3d_mm"], mask.sum() / case.mask.sum(), time.perf_counter() - start,
                         result.rim_offset_px))
        print(f"{condition:>10} {statistics.mean(r[0] for r in rows):7.2f} {statistics.mean(r[1] for r in rows):7.2f}  "
              + " ".join(f"{r[0]:.1f}/{r[1]:.1f}" for r in rows)
              + (" rim " + " ".join(f"{r[4]:+.0f}" for r in rows) if args.auto_rim else "")
              + (" rim " + " ".join(f"{r[4]:+.2f}" for r in rows) if args.image_rim else "")
              + f"  (area x{statistics.mean(r[2] for r in rows):.3f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
