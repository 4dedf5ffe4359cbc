"""How a manipulator's warm fit copes with a jump: one frame fitted from a start turned and scaled off the truth.

The toy arm's views of ``tests/test_track.py`` (``_toy_arm_sequence``, 320x240, seeds 3-5), each mask drawn by the
painter's renderer (``pipeline.synth.pose.painter_mask``, not the fit's) with a 1 px wobbly boundary; starts turned
1.5 or 2 degrees about the camera's z or y axis and moved 2 % or 4 % too far or 3 % too near (12 a view). Each start
is fitted with the tracker's warm fit (``WARM_POSE_FIT``), with the calm fit alone (``calm_pose_fit``), and as
``PoseTrackConfig.calm_fit`` does it at each ``--ratios`` R: the calm fit, and the warm fit too where the calm loss is
above R times a running-loss stand-in (0.7 x the warm fit's loss and 0.3 x the calm fit's, both from the true
pose), the lower loss kept. Prints the root's position error per start and the median / mean / max over all.

    python benchmarks/warm_pose_jumps.py [--ratios 1.2,1.5] [--seeds 3,4,5]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--ratios", default="1.2,1.5", help="calm_ratio values, comma-separated")
    parser.add_argument("--seeds", default="3,4,5", help="views of tests/test_track.py's toy-arm sequence")
    args = parser.parse_args()
    root = Path(__file__).resolve().parents[1]
    sys.path[:0] = [str(root), str(root / "tests")]
    from test_track import _toy_arm_sequence

    from pipeline.pose_estimation import estimate_pose
    from pipeline.synth.pose import corrupt_mask, painter_mask
    from pipeline.track import WARM_POSE_FIT, calm_pose_fit

    ratios = [float(r) for r in args.ratios.split(",")]
    calm_fit = calm_pose_fit()
    names = ["warm fit", "calm fit alone", *(f"calm, fallback at {r:g}" for r in ratios)]
    errors, fallbacks = [], np.zeros(len(ratios), int)
    for seed in (int(s) for s in args.seeds.split(",")):
        model, camera, _, joints, poses = _toy_arm_sequence(1, seed=seed)
        T, q = poses[0], joints[0]
        mask = corrupt_mask(painter_mask(model, q.numpy(), T, camera), np.random.default_rng(seed + 1000),
                            boundary_noise_px=1.0)
        level = (0.7 * estimate_pose(mask, model, q, camera, WARM_POSE_FIT, initial_T_cam_root=T).loss
                 + 0.3 * estimate_pose(mask, model, q, camera, calm_fit, initial_T_cam_root=T).loss)
        for deg, scale, axis in itertools.product((1.5, 2.0), (1.02, 1.04, 0.97), ("z", "y")):
            c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
            R = [[c, -s, 0], [s, c, 0], [0, 0, 1]] if axis == "z" else [[c, 0, s], [0, 1, 0], [-s, 0, c]]
            start = T.copy()
            start[:3, :3] = np.asarray(R) @ start[:3, :3]
            start[:3, 3] *= scale
            warm = estimate_pose(mask, model, q, camera, WARM_POSE_FIT, initial_T_cam_root=start)
            calm = estimate_pose(mask, model, q, camera, calm_fit, initial_T_cam_root=start)
            lower = calm if calm.loss < warm.loss else warm
            fell = np.array([calm.loss > r * level for r in ratios])
            fallbacks += fell
            row = [warm, calm, *(lower if f else calm for f in fell)]
            row = [1000.0 * float(np.linalg.norm(r.T_cam_root[:3, 3] - T[:3, 3])) for r in row]
            errors.append(row)
            print(f"seed {seed}, {deg} deg about {axis}, x{scale}: calm loss {calm.loss / level:.2f} x the level; "
                  + ", ".join(f"{n} {e:.1f} mm" for n, e in zip(names, row)), flush=True)
    errors = np.array(errors)
    print(f"{len(errors)} starts, root position error median / mean / max, mm:")
    for k, name in enumerate(names):
        fell = f" ({fallbacks[k - 2]} fell back)" if k >= 2 else ""
        print(f"  {name}: {np.median(errors[:, k]):.1f} / {errors[:, k].mean():.1f} / {errors[:, k].max():.1f}{fell}")


if __name__ == "__main__":
    main()
