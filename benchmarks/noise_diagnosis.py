"""Why do noisy masks cost centimetres? One segmentation error at a time, the loss at the truth against the loss at
the estimate, and a fit started at the truth.

For each robot, view (seeds ``--seed``, ``--seed + 1``, ...; tune on these, report on ``acceptance_robots.py``'s
5000+) and noise kind (``clean``; ``fingers`` missing; boundary ``jitter`` 1.5 px; a 3 % ``blob``; a 2 px
``dilate`` or ``erode``; an occluding ``box`` of 15-25 % of the mask's extent; ``all``: the benchmark's noisy mask),
it prints the end effector's 3D error and the loss (the last stage's, ``_total_loss``) of:

- ``truth``: the true pose, not optimised;
- ``from truth``: the fit started at the true pose (``initial_T_cam_root``: one start, no random candidates); if it
  drifts away, the loss's optimum is biased (the loss, not the search, is at fault);
- ``fit``: the full multi-start fit; a loss above ``from truth``'s means the search missed the basin.

    python benchmarks/noise_diagnosis.py --robots panda ur5 --views 2 --geometry cad --kinds clean box dilate
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from acceptance_robots import CAMERAS, ROBOTS, noisy_mask, painter_mask, truth_and_model  # noqa: E402

from pipeline.evaluate import point_errors  # noqa: E402
from pipeline.pose_estimation import PoseFitConfig, estimate_pose, pose_loss_at  # noqa: E402
from pipeline.synth.pose import corrupt_mask, random_view  # noqa: E402

KINDS = ("clean", "fingers", "jitter", "blob", "dilate", "erode", "box", "all")


def one_noise(kind: str, truth, q, T, camera, rng: np.random.Generator) -> np.ndarray:
    """The clean mask with one kind of segmentation error (the parameters of ``acceptance_robots.noisy_mask``)."""
    if kind == "all":
        return noisy_mask(truth, q, T, camera, rng)
    if kind == "fingers":
        return painter_mask(truth, q, T, camera, skip_links=tuple(n for n in truth.link_names if "finger" in n))
    mask = painter_mask(truth, q, T, camera)
    scale = camera.image_size[1] / 640.0
    if kind == "jitter":
        return corrupt_mask(mask, rng, boundary_noise_px=1.5 * scale)
    if kind == "blob":
        return corrupt_mask(mask, rng, boundary_noise_px=0.0, blob_fraction=0.03)
    if kind in ("dilate", "erode"):
        return (cv2.dilate if kind == "dilate" else cv2.erode)(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if kind == "box":
        ys, xs = np.nonzero(mask)
        h, w = np.ptp(ys) + 1, np.ptp(xs) + 1
        bh, bw = int(h * rng.uniform(0.15, 0.25)), int(w * rng.uniform(0.15, 0.25))
        k = rng.integers(len(ys))
        y0, x0 = max(ys[k] - bh // 2, 0), max(xs[k] - bw // 2, 0)
        mask = mask.copy()
        mask[y0 : y0 + bh, x0 : x0 + bw] = False
        return mask
    return mask


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", nargs="+", default=["panda", "ur5"], choices=sorted(ROBOTS))
    parser.add_argument("--resolution", default="640", choices=sorted(CAMERAS))
    parser.add_argument("--geometry", default="cad")
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=100, help="views use seeds seed, seed+1, ... (tuning seeds)")
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    parser.add_argument("--no-full-fit", action="store_true", help="only the truth and the fit from the truth")
    parser.add_argument("--config", default="{}", help="PoseFitConfig fields as JSON, e.g. '{\"robust\": true}'")
    parser.add_argument("--out", type=Path, default=Path("out/noise_diagnosis.jsonl"))
    args = parser.parse_args()
    config = PoseFitConfig(**json.loads(args.config))
    camera = CAMERAS[args.resolution]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("a") as log:
        for name in args.robots:
            truth, model, ee = truth_and_model(name, args.geometry)
            for view in range(args.views):
                q, T = random_view(truth, camera, np.random.default_rng(args.seed + view))
                p = truth.link_frames_in_root(torch.from_numpy(q)[None])[0, ee, :3, 3].numpy()
                for kind in args.kinds:
                    mask = one_noise(kind, truth, q, T, camera, np.random.default_rng(10_000 + args.seed + view))
                    row = {"robot": name, "view": args.seed + view, "kind": kind, "geometry": args.geometry,
                           "config": args.config, "loss_truth": pose_loss_at(mask, model, torch.from_numpy(q), camera,
                                                                             T, config)}  # fmt: skip
                    fits = {"from_truth": dict(initial_T_cam_root=T)}
                    if not args.no_full_fit:
                        fits["fit"] = {}
                    for label, extra in fits.items():
                        start = time.perf_counter()
                        result = estimate_pose(mask, model, torch.from_numpy(q), camera, config, **extra)
                        err = point_errors(result.T_cam_root[None], T[None], p[None], camera.K_array())
                        row[f"{label}_mm"] = round(float(err["err_3d_mm"][0]), 1)
                        row[f"{label}_px"] = round(float(err["err_2d_px"][0]), 1)
                        row[f"{label}_loss"] = result.loss
                        row[f"{label}_s"] = round(time.perf_counter() - start, 1)
                        row[f"{label}_boundary_px"] = result.boundary_offset_px
                    log.write(json.dumps(row) + "\n")
                    log.flush()
                    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
