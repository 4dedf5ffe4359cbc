"""Ablations of the manipulator pose fit: which loss terms, and which link geometry.

1. Losses: the same cases (masks from the example robot's primitives, odd cases with 1 px boundary noise and a
   3 % false-positive blob) fitted with ``mask``, ``mask + distance`` and ``mask + distance + appearance``
   (weights 1 or 0; everything else the default PoseFitConfig). The end-effector 3D error per iteration is that of
   the start with the lowest loss at that iteration (the answer if the fit stopped there), averaged over the cases;
   written as ``ablation_losses.png`` and a table.
2. Geometry (the paper's PCK table): masks rendered from the CAD meshes, fitted with one box per link, one
   cylinder per link, the collision geometry (mesh elements as boxes) and the CAD meshes themselves.

    python benchmarks/ablation_losses.py [--cases 8] [--out-dir out/ablation]

Writes ``ablation_losses.png`` and ``ablation.md`` to ``--out-dir`` and prints the tables.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from acceptance_pose import PASS_2D_PX, PASS_3D_MM, run_setting, table  # noqa: E402
from pose_cases import CAMERA, load_average, load_model, make_cases, point_root  # noqa: E402

from pipeline.pose_estimation import PoseFitConfig, estimate_pose  # noqa: E402
from pipeline.viz import plot_history  # noqa: E402

LOSSES = {  # name: (weight_mask, weight_distance, weight_appearance)
    "mask": (1.0, 0.0, 0.0),
    "mask + distance": (1.0, 1.0, 0.0),
    "mask + distance + appearance": (1.0, 1.0, 1.0),
}
COLORS = {"mask": (40, 40, 220), "mask + distance": (220, 120, 0), "mask + distance + appearance": (0, 160, 0)}
CHECKPOINTS = (50, 100, 200, 300, 400, 500)


def error_curve(result, case, model) -> np.ndarray:
    """``(N,)`` end-effector 3D error (mm) of the lowest-loss start at each iteration."""
    history = np.where(np.isfinite(result.history), result.history, np.inf)  # (N, S)
    lead = np.argmin(history, axis=1)  # (N,)
    T = result.trajectory[np.arange(len(lead)), lead]  # (N, 4, 4)
    point = np.append(point_root(model, case.joint_angles), 1.0)
    est = T[:, :3] @ point  # (N, 3)
    true = case.T_cam_root[:3] @ point
    return np.linalg.norm(est - true, axis=1) * 1000.0


def loss_ablation(count: int, seed0: int) -> tuple[dict[str, np.ndarray], dict[str, list[dict]]]:
    model = load_model("primitives", "collision")
    cases = make_cases("primitives", count, seed0)
    curves, finals = {}, {}
    for name, (wm, wd, wa) in LOSSES.items():
        config = PoseFitConfig(weight_mask=wm, weight_distance=wd, weight_appearance=wa, record_trajectory=True)
        rows, per_case = [], []
        for case in cases:
            result = estimate_pose(case.mask, model, torch.from_numpy(case.joint_angles), CAMERA, config)
            curve = error_curve(result, case, model)
            rows.append(curve)
            point = np.append(point_root(model, case.joint_angles), 1.0)
            err_3d = float(np.linalg.norm((result.T_cam_root - case.T_cam_root)[:3] @ point) * 1000.0)
            est_px = CAMERA.K_array() @ (result.T_cam_root[:3] @ point)
            true_px = CAMERA.K_array() @ (case.T_cam_root[:3] @ point)
            err_2d = float(np.linalg.norm(est_px[:2] / est_px[2] - true_px[:2] / true_px[2]))
            per_case.append({"err_3d_mm": err_3d, "err_2d_px": err_2d, "seconds": result.seconds})
            print(f"{name:30s} {case.name:16s} {case.kind:5s} 3D {err_3d:8.1f} mm  2D {err_2d:7.2f} px  "
                  f"{result.seconds:5.1f} s", flush=True)
        curves[name] = np.mean(rows, axis=0)
        finals[name] = per_case
    return curves, finals


def loss_table(curves: dict[str, np.ndarray], finals: dict[str, list[dict]]) -> str:
    head = (["losses", f"pass (<{PASS_2D_PX:g} px & <{PASS_3D_MM:g} mm)", "median 3D mm (final)", "mean 3D mm (final)"]
            + [f"mean 3D mm @ it {c}" for c in CHECKPOINTS])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name, curve in curves.items():
        rows = finals[name]
        e3 = np.array([r["err_3d_mm"] for r in rows])
        ok = np.mean([r["err_2d_px"] < PASS_2D_PX and r["err_3d_mm"] < PASS_3D_MM for r in rows])
        cells = [name, f"{ok:.2f}", f"{np.median(e3):.1f}", f"{e3.mean():.1f}"]
        cells += [f"{curve[min(c, len(curve)) - 1]:.1f}" for c in CHECKPOINTS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot_curves(curves: dict[str, np.ndarray], size: tuple[int, int] = (420, 640)) -> np.ndarray:
    """Mean 3D error (mm, log scale) per iteration, one colour per loss variant, with a legend."""
    return plot_history(np.stack(list(curves.values()), axis=1), title="mean end-effector 3D error (mm)",
                        size=size, labels=list(curves), colors=[COLORS[name] for name in curves])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=8, help="cases per variant (default 8)")
    parser.add_argument("--seed0", type=int, default=2000)
    parser.add_argument("--out-dir", default="out/ablation")
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    start, load = time.perf_counter(), load_average()

    curves, finals = loss_ablation(args.cases, args.seed0)
    cv2.imwrite(str(out / "ablation_losses.png"), plot_curves(curves))
    losses_md = loss_table(curves, finals)
    print("\n" + losses_md)

    config = PoseFitConfig()
    geometry = [run_setting(name, args.cases, args.seed0, config) for name in ("box", "cylinder", "collision", "cad")]
    geometry_md = table(geometry)
    print("\n" + geometry_md)
    note = (f"{args.cases} cases per row (seeds {args.seed0}-{args.seed0 + args.cases - 1}; odd ones with 1 px "
            f"boundary noise and a 3 % false-positive blob), 640x480, default PoseFitConfig unless stated; "
            f"{time.perf_counter() - start:.0f} s in all, load average {load} at the start, {load_average()} at "
            f"the end (2 cores).")
    (out / "ablation.md").write_text(
        "## Losses (masks from the primitives, fitted with them)\n\n" + losses_md
        + "\n\n![mean 3D error per iteration](ablation_losses.png)\n\n"
        + "## Geometry (masks from the CAD meshes)\n\n" + geometry_md + "\n\n" + note + "\n"
    )  # fmt: skip
    print("\n" + note + f"\nwritten to {out}/")


if __name__ == "__main__":
    main()
