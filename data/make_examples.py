"""Write the bundled synthetic soft-arm examples into data/soft_arm/ (deterministic: fixed seeds).

Run from the repository root: ``python data/make_examples.py``. Each example folder holds
``image.png`` (BGR, 640x360), ``mask.png`` (uint8 0/255), ``camera.json`` (the project's camera format) and
``truth.json`` (centreline in the camera frame, metres: 101 points uniform in arc length from base to tip, the
radii at those points, and for Bezier arms the control points).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.io import write_image, write_json, write_mask  # noqa: E402
from pipeline.shapes.polyline import bezier_centerline  # noqa: E402
from pipeline.synth.soft_arm import pcc_arm, random_bezier_arm, render_tube_image  # noqa: E402

OUT = Path(__file__).resolve().parent / "soft_arm"
H, W = 360, 640
K = np.array([[520.0, 0.0, (W - 1) / 2], [0.0, 520.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
LENGTH_M, BASE_RADIUS_M, TIP_RADIUS_M, DISTANCE_M = 0.2, 0.014, 0.006, 0.42
N_POINTS = 101

EXAMPLES = [
    # name, seed, model, options
    ("quadratic", 3, "bezier", {"order": 2}),
    ("cubic_s", 8, "bezier", {"order": 3, "max_bend_rad": 3.0}),  # an S in the image
    ("pcc", 7, "pcc", {"n_segments": 2}),
]


def main() -> None:
    camera = {"K": K.tolist(), "dist": [], "width": W, "height": H}
    radii = np.linspace(BASE_RADIUS_M, TIP_RADIUS_M, N_POINTS)
    for name, seed, model, options in EXAMPLES:
        rng = np.random.default_rng(seed)
        truth = {
            "model": model,
            "seed": seed,
            "length_m": LENGTH_M,
            "base_radius_m": BASE_RADIUS_M,
            "tip_radius_m": TIP_RADIUS_M,
        }
        if model == "bezier":
            control_points = random_bezier_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, **options)
            centerline = bezier_centerline(control_points, N_POINTS)
            truth.update(order=options["order"], control_points_cam_m=control_points)
        else:
            centerline = pcc_arm(
                rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, n_points=N_POINTS, **options
            )
            truth.update(n_segments=options["n_segments"])
        truth.update(centerline_cam_m=centerline, radii_m=radii)
        image, mask = render_tube_image(centerline, radii, K, (H, W), rng)
        folder = OUT / name
        write_image(folder / "image.png", image)
        write_mask(folder / "mask.png", mask)
        write_json(folder / "camera.json", camera)
        write_json(folder / "truth.json", truth)
        print(f"{folder}: {int(mask.sum())} mask pixels")


if __name__ == "__main__":
    main()
