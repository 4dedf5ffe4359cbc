"""Synthetic soft-arm cases shared by the shape benchmarks: a random arm, its image and exact mask, its truth.

Set-up of the acceptance criterion: 1280x720 image, fx = fy = 700 px, principal point at the centre, a 200 mm arm
(radius 14 mm at the base, 6 mm at the tip, linear in arc length) whose centreline's centroid is 0.4 m from the
camera, drawn whole in the image with its base nearer the image border (``pipeline.synth.soft_arm``).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.camera import Camera  # noqa: E402
from pipeline.robots import ContinuumRobot  # noqa: E402
from pipeline.shapes.polyline import bezier_centerline  # noqa: E402
from pipeline.synth.soft_arm import (DEFAULT_ARM_COLOR_BGR, pcc_arm, pcc_centerline, place_in_view,  # noqa: E402
                                     random_bezier_arm, render_tube_image)

H, W = 720, 1280
K = np.array([[700.0, 0.0, (W - 1) / 2], [0.0, 700.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
CAMERA = Camera(K=K.tolist(), width=W, height=H)
LENGTH_M, BASE_RADIUS_M, TIP_RADIUS_M, DISTANCE_M = 0.2, 0.014, 0.006, 0.4

#: Kinds of arm: a random quadratic Bezier, a cubic that may bend both ways (an S), two constant-curvature arcs,
#: and the issue-13 set: two 100 mm constant-curvature sections, each of curvature uniform in [0, 15] 1/m and a
#: bending plane uniform in [0, 2 pi) (so S shapes and out-of-plane bends), in a random arm colour.
KINDS = ("quadratic", "cubic_s", "pcc", "two_section")

#: Largest curvature of a ``two_section`` arm's section, 1/m.
MAX_CURVATURE_PER_M = 15.0


@dataclass(frozen=True)
class ShapeCase:
    seed: int
    kind: str
    image: np.ndarray  # (H, W, 3) uint8 BGR
    mask: np.ndarray  # (H, W) bool
    truth_cam_m: np.ndarray  # (201, 3) centreline, uniform in arc length, base to tip


def make_case(seed: int, kind: str = "quadratic", supersample: int = 4) -> ShapeCase:
    """One synthetic arm of ``kind`` from ``numpy.random.default_rng(seed)``.

    The arm is drawn area-averaged (``render_tube_image(supersample=4)``): its rim pixels mix arm and background
    by covered area, as a camera's do, so a perfect segmentation of the image has the exact mask's area
    (``supersample=1``: OpenCV's anti-aliased fill, 0.66 px wider on every side). The mask and the truth do not
    depend on it."""
    rng = np.random.default_rng(seed)
    if kind == "quadratic":
        control = random_bezier_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, order=2)
        truth = bezier_centerline(control, 201)
    elif kind == "cubic_s":
        control = random_bezier_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, order=3,
                                    max_bend_rad=3.0)
        truth = bezier_centerline(control, 201)
    elif kind == "pcc":
        truth = pcc_arm(rng, K, (H, W), length_m=LENGTH_M, distance_m=DISTANCE_M, n_segments=2, n_points=201)
    elif kind == "two_section":
        curvatures = rng.uniform(0.0, MAX_CURVATURE_PER_M, 2)
        planes = rng.uniform(0.0, 2.0 * np.pi, 2)
        local = pcc_centerline(list(curvatures), list(planes), [LENGTH_M / 2] * 2, 201)
        truth = place_in_view(rng, local, K, (H, W), distance_m=DISTANCE_M)
    else:
        raise ValueError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
    radii = np.linspace(BASE_RADIUS_M, TIP_RADIUS_M, len(truth))
    colour = DEFAULT_ARM_COLOR_BGR if kind != "two_section" else random_arm_colour(rng)
    image, mask = render_tube_image(truth, radii, K, (H, W), rng, arm_color_bgr=colour,
                                    supersample=supersample)
    return ShapeCase(seed=seed, kind=kind, image=image, mask=mask, truth_cam_m=truth)


def random_arm_colour(rng: np.random.Generator) -> tuple[int, int, int]:
    """A BGR arm colour of uniform hue, saturation in [0.4, 1] and value in [0.35, 0.95]."""
    hsv = np.uint8([[[rng.uniform(0, 180), rng.uniform(0.4, 1.0) * 255, rng.uniform(0.35, 0.95) * 255]]])
    return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])


def robot() -> ContinuumRobot:
    """The arm as the user describes it: length and radii."""
    return ContinuumRobot(length_m=LENGTH_M, base_radius_m=BASE_RADIUS_M, tip_radius_m=TIP_RADIUS_M)
