"""What the pose fit's retry buys: both attempts (seed 0, then seed 1, as the retry runs it) on views of real robots.

For each robot of ``acceptance_robots.py`` (``example-robot-data``), ``--views`` random views (seeds ``--seed``,
``--seed`` + 1, ...; the default 6000 are tuning views, apart from the benchmark's 5000+), a clean mask from the
full visual meshes by the painter's renderer, 640x480; ``estimate_pose`` with ``PoseFitConfig(seed=s,
retries=0)`` for s = 0 and 1. Prints one JSON line per view: each attempt's loss, end-effector 3D mm, 2D px and
seconds. The default fit retries when the first loss is above ``retry_loss`` (0.15) and keeps the lower loss.

    python benchmarks/retry_study.py --geometry collision --views 3 --robots panda ur5 baxter
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from acceptance_robots import CAMERAS, ROBOTS, truth_and_model

from pipeline.evaluate import point_errors
from pipeline.pose_estimation import PoseFitConfig, estimate_pose
from pipeline.synth.pose import painter_mask, random_view


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--geometry", default="collision", choices=["collision", "box", "cylinder", "hull", "cad"])
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--seed", type=int, default=6000)
    parser.add_argument("--robots", nargs="+", default=["panda", "ur5", "baxter"], choices=sorted(ROBOTS))
    args = parser.parse_args()
    camera = CAMERAS["640"]
    for name in args.robots:
        truth, model, ee = truth_and_model(name, args.geometry)
        for view in range(args.views):
            q, T = random_view(truth, camera, np.random.default_rng(args.seed + view))
            mask = painter_mask(truth, q, T, camera)
            p = truth.link_frames_in_root(torch.from_numpy(q)[None])[0, ee, :3, 3].numpy()
            attempts = []
            for seed in (0, 1):
                r = estimate_pose(mask, model, torch.from_numpy(q), camera, PoseFitConfig(seed=seed, retries=0))
                e = point_errors(r.T_cam_root[None], T[None], p[None], camera.K_array())
                attempts.append({"loss": round(r.loss, 4), "err_3d_mm": round(float(e["err_3d_mm"][0]), 1),
                                 "err_2d_px": round(float(e["err_2d_px"][0]), 1), "seconds": round(r.seconds, 1)})
            print(json.dumps({"robot": name, "geometry": args.geometry, "view": args.seed + view,
                              "attempts": attempts}), flush=True)


if __name__ == "__main__":
    main()
