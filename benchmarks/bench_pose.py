"""Seconds per manipulator pose estimate at 640x480 (500 iterations), ours versus the paper's setting.

- ``ours``: the default PoseFitConfig: 512 scored candidate rotations, 4 stages (link hulls at 80x60 with 32
  starts, at 160x120 with the best 8, at 320x240 with the best 2, the meshes at 640x480 with the best 1),
  straight-through silhouette, back faces culled, sigma 0.5 px^2.
- ``ours-8``: the same with 8 starts from the beginning (3 stages: 160x120 with 8, 320x240 with 2, 640x480 with 1).
- ``paper``: one stage at 640x480 with all 8 starts for all 500 iterations, 8 random rotations (no scoring), the
  soft silhouette (sigma 5.76 px^2 = PyTorch3D's 1e-4, cut-off where a face's probability is 1e-4, no culling),
  constant learning rates 1e-2 (pose) and 1e-4 (offsets), no outlier rejection, no retry, no polish; our
  parametrisation and losses.

    python benchmarks/bench_pose.py [--cases 5] [--paper-cases 2] [--real-robots baxter panda ur5 --real-cases 2]

``--real-robots``: also time the default fit (``collision``) and the CAD fit (``cad``, meshes decimated to 3000
faces per link) on robots of the ``example-robot-data`` package (masks from their full visual meshes by the
painter's renderer of ``acceptance_robots.py``), at 640x480 and at 2048x1536 with distortion; seconds per fit and
per iteration (``seconds / iterations``, all stages).

Prints per-case wall and CPU seconds with the end-effector errors, and the medians. Other processes on the machine
slow the wall time down; the load average is printed with the results.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from pose_cases import CAMERA, case_errors, load_average, load_model, make_cases  # noqa: E402

from pipeline.pose_estimation import PoseFitConfig, PoseStage, estimate_pose  # noqa: E402

CONFIGS = {
    "ours": PoseFitConfig(),
    "ours-8": PoseFitConfig(starts=8, stages=(
        PoseStage(fraction=0.4, scale=0.25, keep=8, sigma_px2=0.5, hull=True),
        PoseStage(fraction=0.3, scale=0.5, keep=2, sigma_px2=0.5, hull=True),
        PoseStage(fraction=0.3, scale=1.0, keep=1, sigma_px2=0.5, lr_scale=0.3, final_lr_factor=0.1),
    )),
    "paper": PoseFitConfig(
        starts=8, candidates=8, min_start_separation_deg=0.0, cutoff_eps=1e-4, cull_back_faces=False,
        drop_unexplained=False, retries=0, polish_newton_steps=0, polish_rounds=0,
        stages=(PoseStage(fraction=1.0, scale=1.0, keep=8, sigma_px2=5.76, straight_through=False),),
    ),
}


def bench(name: str, cases, model) -> list[dict]:
    rows = []
    for case in cases:
        cpu = time.process_time()
        result = estimate_pose(case.mask, model, torch.from_numpy(case.joint_angles), CAMERA, CONFIGS[name])
        cpu = time.process_time() - cpu
        err = case_errors(model, case, result.T_cam_root)
        rows.append({"wall": result.seconds, "cpu": cpu, **err})
        print(f"{name:6s} {case.name:16s} {result.seconds:7.2f} s wall {cpu:7.2f} s CPU   "
              f"2D {err['err_2d_px']:7.2f} px  3D {err['err_3d_mm']:7.1f} mm  (load {load_average()})", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=5, help="clean cases timed with the default config")
    parser.add_argument("--paper-cases", type=int, default=2, help="the first cases again with the paper's setting")
    parser.add_argument("--seed0", type=int, default=3000)
    parser.add_argument("--real-robots", nargs="*", default=[], help="e.g. baxter panda ur5 (example-robot-data)")
    parser.add_argument("--real-cases", type=int, default=2, help="views per real robot and resolution")
    args = parser.parse_args()
    model = load_model("primitives", "collision")
    cases = make_cases("primitives", max(args.cases, args.paper_cases), args.seed0, corrupted_every=0)
    warm = cases[0]  # numba kernels compile (or load from the cache) on the first call
    estimate_pose(warm.mask, model, torch.from_numpy(warm.joint_angles), CAMERA, PoseFitConfig(iterations=8))
    results = {name: bench(name, cases[: args.cases], model) for name in ("ours", "ours-8")}
    if args.paper_cases:
        results["paper"] = bench("paper", cases[: args.paper_cases], model)
    print("\n| config | cases | median s (wall) | median s (CPU) | median 2D px | median 3D mm | "
          "pass (<5 px & <10 mm) |\n|---|---|---|---|---|---|---|")
    for name, rows in results.items():
        med = {k: float(np.median([r[k] for r in rows])) for k in ("wall", "cpu", "err_2d_px", "err_3d_mm")}
        ok = np.mean([r["err_2d_px"] < 5 and r["err_3d_mm"] < 10 for r in rows])
        print(f"| {name} | {len(rows)} | {med['wall']:.1f} | {med['cpu']:.1f} | {med['err_2d_px']:.2f} | "
              f"{med['err_3d_mm']:.1f} | {ok:.2f} |")
    print(f"\n640x480, 500 iterations; torch {torch.__version__}, 2 CPU cores shared with other processes "
          f"(load average now {load_average()}).")
    if args.real_robots:
        bench_real_robots(args.real_robots, args.real_cases)


def bench_real_robots(names: list[str], views: int) -> None:
    from acceptance_robots import CAMERAS, ROBOTS
    from pipeline.synth.pose import painter_mask

    from pipeline.evaluate import point_errors
    from pipeline.robots import load_robot
    from pipeline.synth.pose import random_view

    print("\n| robot | resolution | geometry | faces | median s per fit | median ms per iteration | median 2D px | "
          "median 3D mm |\n|---|---|---|---|---|---|---|---|")  # fmt: skip
    for name in names:
        robot = ROBOTS[name]
        truth = load_robot(robot.path, robot.root, primitive="cad", cad_faces=10**9, cad_faces_per_cm2=None,
                           mesh_cache=None)
        ee = truth.frame_index(robot.end_effector)
        for resolution, camera in CAMERAS.items():
            cases = []
            for view in range(views):
                q, T = random_view(truth, camera, np.random.default_rng(7000 + view))
                cases.append((q, T, painter_mask(truth, q, T, camera)))
            for geometry in ("collision", "cad"):
                model = load_robot(robot.path, robot.root, primitive=geometry)
                rows = []
                for q, T, mask in cases:
                    result = estimate_pose(mask, model, torch.from_numpy(q), camera, PoseFitConfig())
                    p = truth.link_frames_in_root(torch.from_numpy(q)[None])[0, ee, :3, 3].numpy()
                    err = point_errors(result.T_cam_root[None], T[None], p[None], camera.K_array())
                    rows.append((result.seconds, 1e3 * result.seconds / result.iterations,
                                 float(err["err_2d_px"][0]), float(err["err_3d_mm"][0])))  # fmt: skip
                s, ms, px, mm = np.median(np.array(rows), axis=0)
                print(f"| {name} | {resolution} | {geometry} | {len(model.faces)} | {s:.1f} | {ms:.1f} | {px:.1f} | "
                      f"{mm:.1f} |  (load {load_average()})", flush=True)


if __name__ == "__main__":
    main()
