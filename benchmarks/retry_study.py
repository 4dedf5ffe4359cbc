"""What the pose fit's retry buys: both attempts (seed 0, then seed 1, as the retry runs it), stage by stage.

Real robots (``--robots``, of ``acceptance_robots.py``, ``example-robot-data``): ``--views`` random views (seeds
``--seed``, ``--seed`` + 1, ...; the default 6000 are tuning views, apart from the benchmark's 5000+), a clean mask
from the full visual meshes by the painter's renderer, 640x480. The project's toy arm (``--toy cad`` or
``primitives``): the cases of ``acceptance_pose.py`` (``make_cases``, seeds ``--toy-seed0``...; the second attempt
only where the first one's loss is above ``retry_loss``, the cases where the retry runs). Each attempt is
``estimate_pose`` with ``PoseFitConfig(seed=s, retries=0)``; one JSON line per view: each attempt's loss, the best
loss at the end of each stage (``stage_best``, which a retry rule may compare), end-effector 3D mm, 2D px, seconds.

    python benchmarks/retry_study.py --geometry collision --views 3 --robots panda ur5 baxter
    python benchmarks/retry_study.py --robots --toy cad --toy-cases 40 --toy-seed0 3000
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch
from acceptance_robots import CAMERAS, ROBOTS, truth_and_model
from pose_cases import CAMERA, case_errors, load_model, make_cases

from pipeline.evaluate import point_errors
from pipeline.pose_estimation import PoseFitConfig, PoseResult, estimate_pose, stage_best_losses
from pipeline.synth.pose import painter_mask, random_view


def attempt(mask, model, q, camera, seed: int) -> tuple[PoseResult, dict]:
    config = PoseFitConfig(seed=seed, retries=0)
    r = estimate_pose(mask, model, torch.from_numpy(q), camera, config)
    best = [round(v, 4) for v in stage_best_losses(r.history, config)]
    return r, {"loss": round(r.loss, 4), "stage_best": best, "seconds": round(r.seconds, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--geometry", default="collision", choices=["collision", "box", "cylinder", "hull", "cad"])
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--seed", type=int, default=6000)
    parser.add_argument("--robots", nargs="*", default=["panda", "ur5", "baxter"], choices=sorted(ROBOTS))
    parser.add_argument("--toy", choices=["cad", "primitives"], help="also the toy arm's acceptance cases")
    parser.add_argument("--toy-cases", type=int, default=40)
    parser.add_argument("--toy-seed0", type=int, default=3000)
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
                r, row = attempt(mask, model, q, camera, seed)
                e = point_errors(r.T_cam_root[None], T[None], p[None], camera.K_array())
                attempts.append({**row, "err_3d_mm": round(float(e["err_3d_mm"][0]), 1),
                                 "err_2d_px": round(float(e["err_2d_px"][0]), 1)})
            print(json.dumps({"robot": name, "geometry": args.geometry, "view": args.seed + view,
                              "attempts": attempts}), flush=True)
    if args.toy:
        truth_kind, primitive = {"cad": ("cad", "cad"), "primitives": ("primitives", "collision")}[args.toy]
        model = load_model(truth_kind, primitive)
        for case in make_cases(truth_kind, args.toy_cases, args.toy_seed0):
            attempts = []
            for seed in (0, 1):
                r, row = attempt(case.mask, model, case.joint_angles, CAMERA, seed)
                err = case_errors(model, case, r.T_cam_root)
                attempts.append({**row, "err_3d_mm": round(float(err["err_3d_mm"]), 1),
                                 "err_2d_px": round(float(err["err_2d_px"]), 1)})
                if r.loss <= PoseFitConfig().retry_loss:
                    break
            print(json.dumps({"robot": f"toy-{args.toy}", "case": case.name, "kind": case.kind,
                              "attempts": attempts}), flush=True)


if __name__ == "__main__":
    main()
