"""Shape of a soft continuum robot from one binary mask (DESIGN.md 1.1): fit a Bezier tube by soft rendering.

Convention: camera frame (OpenCV: x right, y down, z forward), metres; pixels ``(u, v)`` = (column, row) with pixel
centres at integers, in the *undistorted* image (the mask is undistorted with the camera's coefficients first).

Steps of :func:`reconstruct_shape`:

1. Observation (:func:`observe_mask`): undistort the mask, join pieces of the arm cut apart by an occluder
   (``pipeline.preprocess.join_pieces``), keep its largest component, crop it around the robot
   (a quarter of its size as margin) and shrink the crop to the working resolution (longest side at most
   ``config.working_max_side``); the target of the mask term is each working pixel's *coverage* by the
   full-resolution mask (anti-aliased, so sub-pixel edges survive the shrinking). The skeleton path from base to
   tip, the mask's apparent radius along it (coverage integrated across the path) and the observed keypoints at
   fractions ``s_j`` of the path's length (``pipeline.preprocess``).
2. Hypotheses (:func:`initial_control_points`): the path back-projected at depths read from the apparent width
   and the known radii (``z = f r / r_px``) and from slopes and bends of that depth profile, each scaled about the
   camera centre to the known length; Bezier control points fitted to them. All lie in the camera frustum.
3. Pre-fit (no rendering, ``prefit_iterations``, all ``prefit_starts`` hypotheses in one batch): the projected
   centreline against 32 points along the skeleton path, the model's apparent width against the mask's, and the
   length; Adam steps, or Levenberg-Marquardt steps (``prefit_solver="lm"``, ``prefit_levenberg_marquardt``: the
   warm fits' default). One render of every hypothesis picks the ``starts`` that go on.
4. Fit (``pipeline.optimize.fit``, the starts in one render batch, then the best ``finalists``, then the best
   alone; ``_race``): state = each control point's ray and log depth (``control_points_to_state``) and per-ring
   radius offsets; loss per start

       L = w_mask * sum_px (S - M)^2 / A  +  w_keypoint * mean_j |x_j_model - x_j| / P  +  w_length ((l - L) / L)^2

   at the working resolution, with ``M`` the coverage, ``A`` its sum (the mask area, px) and ``P`` the observed
   path length (px): the first two terms are dimensionless (a fraction of the mask area; a fraction of the arm's
   image length), so the default weights hold for any image size and arm size; ``l`` is the model's length and
   ``L`` the robot's. The model keypoint ``x_j_model`` lies at the same fraction ``s_j`` of the *projected*
   centreline's arc length as the observed keypoint on the skeleton path (not at Bezier parameter ``s_j``),
   measured on the part inside the image only (an arm cut by the border is matched on its visible part; the
   mask term cannot see the model outside the image either). Like the skeleton path, the model path runs from
   the outer edge of the base cap to the outer edge of the tip cap.
5. Order (``config.order = "auto"``, the default): the best start's curve is elevated to the next Bezier order
   (exactly, one more control point) and refined for ``order_iterations``, beside ``order_starts - 1`` fresh
   hypotheses of that order from the mask (steps 2-3 again: a quadratic that took the wrong bend is not a good
   start for the cubic), up to order 5, while the loss plus ``order_penalty`` per extra control point keeps
   falling and the curve does not bend tighter than ``max_bend`` (unless the order before did); the
   lowest-scoring order is the answer (``docs/soft-arms.md``).
6. Result: the chosen order's state, the centreline resampled uniform in arc length, at full resolution.

With ``config.model = "auto"`` (the default, :func:`_reconstruct_lower`) the Bezier fit below and its refinement
as PCC sections both run, and the one of lower loss is the answer.
With ``config.model = "pcc"`` (:func:`_reconstruct_pcc`) the centreline is ``config.sections`` constant-curvature
arcs (``pipeline.shapes.pcc``) instead. By default (``pcc_start="bezier"``) steps 1-5 run as above and the Bezier
answer's centreline (and each other order's curve, a start each) is turned into sections (``_pcc_initial_state``:
the arcs through its points, then least squares) and refined by ``pcc_iterations`` rendered steps on that state
(base point, base frame, bend vectors, length logits); :func:`refine_pcc` is that refinement of a given Bezier
fit, with another start beside it (a video's last frame, ``pipeline.track``). With ``pcc_start="hypotheses"`` the
hypotheses of step 2 (at Bezier order ``PCC_HYPOTHESIS_ORDER``) are turned into sections instead, then steps 3
and 4 run on them, with no order step: the PCC model's own search, which ends far from the truth more often
(``docs/soft-arms.md``).

The method and its figures: ``docs/method.md``, ``docs/accuracy.md``.

Threads. While :func:`reconstruct_shape` runs, torch is set to one thread (and restored afterwards;
``pipeline.render.single_torch_thread``): its tensors are small, and on a busy 2-core machine torch's OpenMP
workers made a fit up to 10x slower (the rasterizer's numba kernels keep their own threads).
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import logging
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import pytorch_kinematics as pk
import torch

from pipeline._path_numba import PathPoints
from pipeline._radii_numba import RenderRadii
from pipeline._tube_loss_numba import (BezierChain, BezierTubeLoss, SkeletonLoss, TubeLoss, TubeLossTerms,
                                      bezier_skeleton_terms, bezier_tube_loss, bezier_tube_loss_gradients,
                                      tube_outline)
from pipeline.camera import (
    Camera,
    check_image_matches_camera,
    project_points,
    resize_image,
    undistort_image,
    working_camera,
)
from pipeline.checks import check_choice, check_positive, numba_path
from pipeline.errors import ConfigError, ShapeError
from pipeline.geometry import rotvec_to_rotmat
from pipeline.losses import keypoint_loss, mask_loss
from pipeline.optimize import AdamMoments, FitResult, ParamGroup, fit
from pipeline.preprocess import (arc_length_keypoints, check_mask, clean_mask, exact_distance_transform,
                                 join_pieces, one_piece, piece_ends, skeleton_path)
from pipeline.render import SoftRasterSettings, render_hard, render_silhouette, single_torch_thread
from pipeline.robots.continuum import ContinuumRobot
from pipeline.segment.rim import image_rim_offset_px
from pipeline.shapes.bezier import bernstein_basis, bezier_derivative, bezier_points, elevate_bezier_degree
from pipeline.shapes.frames import FRENET_EPS, Frames, bezier_frames, bezier_weights, initial_normal, unit
from pipeline.shapes.pcc import bend_to_curvature_plane, pcc_points_frames, pcc_section_fractions
from pipeline.shapes.polyline import bezier_centerline, polyline_arc_length, resample_polyline
from pipeline.shapes.tube import ring_parameters, tube_faces, tube_vertices

__all__ = [
    "AUTO_ORDERS",
    "KEYPOINT_MODES",
    "MODELS",
    "PccParameters",
    "ShapeFitConfig",
    "ShapeObservation",
    "ShapeResult",
    "observe_mask",
    "initial_control_points",
    "reconstruct_shape",
    "reconstruct_shapes_warm",
    "refine_pcc",
    "RimSearch",
    "search_rim_offset",
    "reconstruct_shape_from_image",
    "choose_arm_component",
    "sharpest_bend",
    "follow_arm_component",
    "render_shape_mask",
    "draw_shape_overlay",
    "soft_edge_offset_px",
    "soft_edge_offsets_px",
    "calibrate_soft_edge_offsets",
    "control_points_to_state",
    "state_to_control_points",
]

log = logging.getLogger(__name__)

#: Loss variants of the paper's Table I: mask only, mask + the tip, mask + ``k`` keypoints along the arm.
KEYPOINT_MODES = ("mask", "endpoint", "keypoints")

#: Centreline models of ``ShapeFitConfig.model``: a Bezier curve, piecewise constant curvature sections, or
#: ``"auto"``: the Bezier fit and the PCC sections refined from it, the lower loss kept.
MODELS = ("bezier", "pcc", "auto")
PREFIT_SOLVERS = ("adam", "lm")
#: Starts of the PCC fit (``ShapeFitConfig.pcc_start``): the Bezier fit's answer, or the mask's hypotheses.
PCC_STARTS = ("bezier", "hypotheses")

#: Bezier orders that ``ShapeFitConfig(order="auto")`` fits in turn.
AUTO_ORDERS = (2, 3, 4, 5)

#: Points of the centreline written to results (uniform in arc length, base to tip).
CENTERLINE_POINTS = 101

#: Bezier order of the hypotheses the PCC fit starts from (``initial_control_points``; 5 follows S shapes).
PCC_HYPOTHESIS_ORDER = 5

#: Points per section of the PCC centreline resampled into ``centerline_cam_m``.
PCC_DENSE_SAMPLES = 200

#: Margin around the mask's bounding box kept in the working image, as a fraction of the box's longest side.
CROP_MARGIN = 0.25

#: The rendered loss on CPU as one compiled autograd node (``_tube_loss_numba.TubeLoss``; the same loss and
#: gradients as the tensor path to float rounding), the pre-fit's loss likewise (``SkeletonLoss``), and its terms
#: without gradient (Levenberg-Marquardt) from one compiled outline pass (``tube_outline``); False takes the tensor
#: path everywhere (tests compare the two).
FUSED_LOSS = True

#: Points along the skeleton path that the pre-fit matches (at fractions j / 32 of its length, j = 1..32).
SKELETON_POINTS = 32

#: Rounds of solving the path points' 3D arc-length fractions and their width depths together
#: (``initial_control_points``' hypotheses 4 and 5).
CONSISTENT_TAPER_ROUNDS = 3


def _int_at_least(value: int, low: int, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"{name}: expected an int >= {low}, got {value!r}")


@dataclass(frozen=True, kw_only=True)
class ShapeFitConfig:
    """Settings of :func:`reconstruct_shape`; the defaults work for any image size.

    Fields:
        order: Bezier order ``n`` of the centreline (``n + 1`` control points; the paper's is 2), or ``"auto"``:
            fit the orders ``AUTO_ORDERS`` (2 to 5) in turn and keep the one of lowest score ``loss + order_penalty
            * (n - 2)``. The first order gets the whole fit below; each further order starts from the previous
            order's best curve written with one more control point (exact degree elevation, so it starts at the
            same loss) and runs ``order_iterations`` more steps of the rendered fit, beside fresh hypotheses
            (``order_starts``); the first order whose score is not lower than the best so far ends the search (the
            higher orders are not fitted).
        model: the centreline model: ``"auto"`` (default since 2026-12-06, session 60; ``"bezier"`` before): both
            below, the lower loss kept: the Bezier fit (``order``, its search included), then its curve refined as
            ``sections`` arcs as ``"pcc"`` does with ``pcc_start="bezier"`` (which it requires), in the time of a
            ``"pcc"`` fit (the result's ``model`` says which was kept, ``model_losses`` holds both; with
            ``rim_offset_px="auto"`` the offset is searched with the Bezier fit and the arcs refined at the offset
            kept). On the 60 two-section tuning arms 2.48 / 3.84 -> 2.34 / 3.64 px / mm mean (median 1.32 ->
            0.95 px), on 40 single-bend ones 1.22 / 2.11 -> 1.21 / 2.09, for about 15 % more time
            (``docs/soft-arms.md``). ``"bezier"``: a Bezier curve of ``order``, the fit warm starts, held bases,
            batches and trackers use; ``"pcc"``: piecewise constant curvature, ``sections`` circular arcs
            (``pipeline.shapes.pcc``), kept whatever their loss.
        sections: number of constant-curvature sections with ``model="pcc"`` (and ``"auto"``; the same for
            ``section_lengths_m``, ``pcc_start`` and ``pcc_iterations``).
        section_lengths_m: with ``model="pcc"``, the sections' lengths (metres, ``sections`` values summing to the
            robot's length), or empty: the lengths are fitted, their sum held at the robot's length.
        pcc_start: with ``model="pcc"``, what the sections start from: ``"bezier"`` (default): the Bezier fit of
            these settings (its order search included) is run first, and its centreline, turned into ``sections``
            arcs, is refined for ``pcc_iterations`` rendered steps; ``"hypotheses"``: the mask's hypotheses turned
            into arcs race as the Bezier fit's starts do (``starts``, ``iterations``; the PCC fit before
            2026-11-29). On 30 two-section tuning arms the Bezier start's answers were 1.89 px / 4.10 mm off on
            average against the hypotheses' 5.07 / 12.77, for the Bezier fit's time plus about 1.7 s (one
            thread; ``docs/soft-arms.md``).
        pcc_iterations: with ``pcc_start="bezier"``, the rendered steps refining the sections, at the rates of the
            second half of a fit (from ``final_lr_factor ** 0.5`` of the full rate down to ``final_lr_factor``). 50
            since 2026-12-06 (was 150): on the 60 two-section tuning arms the lower loss of the two models gave
            2.34 / 3.64 px / mm at 50 steps, 2.32 / 3.59 at 75, 2.34 / 3.61 at 100, 2.32 / 3.61 at 150, the
            sections alone 2.51 / 4.30 at 50 and 2.46 / 4.74 at 150 (``docs/soft-arms.md``).
        iterations: Adam steps (loss evaluations) of the (first) order's fit.
        order_iterations: Adam steps of each further order with ``order="auto"``.
        order_starts: starts of each further order with ``order="auto"``: the previous order's best curve, elevated,
            and the best ``order_starts - 1`` of ``order_hypotheses`` fresh hypotheses of this order from the mask
            (``initial_control_points``, then the pre-fit, then one render picks them). They run in one batch for
            ``multi_start_fraction`` of the ``order_iterations``, then the lowest goes on alone. 1: the elevated
            curve only (the search before 2026-11-24; ``docs/soft-arms.md``); 2 until 2026-11-25 (3: two fresh
            starts, 2.79 -> 2.52 px mean on the 60 two-section tuning arms, "A longer race" there).
        order_hypotheses: fresh hypotheses pre-fitted at each further order (with ``order_starts > 1``): the first
            ``order_hypotheses`` of ``initial_control_points``' (6: its deterministic ones, the 3D arc-length taper's
            included).
        order_warmup_iterations: with ``order_starts > 1``, steps the fresh starts of each further order run alone
            before they race the elevated curve, at the rate the first order's steps had (from the full rate down
            to that of the first order's step ``iterations * multi_start_fraction``): the elevated curve starts
            converged and a fresh start does not, so without them the race kept the elevated curve's basin even
            where the fresh start's was far lower (``docs/soft-arms.md``, "The race was unfair"). ``None`` (default):
            as many as the first order's starts ran together, ``round(iterations * multi_start_fraction)`` (60);
            0: no warm-up (the search before this field existed).
        order_penalty: with ``order="auto"``, added to an order's loss per control point beyond the first order's;
            an order is kept only when it lowers the loss by more (see ``docs/soft-arms.md`` for how it was chosen).
        max_bend: with ``order="auto"``, a further order is not chosen (and the search ends) when its centreline
            bends tighter than this where the order before it did not: the largest curvature times the tube's
            radius there (``sharpest_bend``; 1 folds the tube's inner side to nothing, 0.5 is a bend radius of two
            tube radii; the project's arms stay below 0.34). Such loops are how a higher order covers a
            false-positive blob touching the arm (``docs/soft-arms.md``); 0: no limit (the search before
            2026-11-28).
        starts: hypotheses optimised together in one render batch; the best is kept (see ``prefit_starts``,
            ``multi_start_fraction`` and ``finalists``). 8 since 2026-11-25 (was 4): the render after the pre-fit
            ranks the starts poorly (on 60 single-bend tuning arms the start that ends lowest was among its first
            4 on 20 arms, its first 8 on 33), and with 8 and the finalists the kept start ends > 5 % above the
            best of all 18 on 6 arms instead of 15 (``docs/soft-arms.md``, "A longer race").
        finalists: after the ``starts`` ran together (``multi_start_fraction``), the ``finalists`` of lowest loss
            go on together to ``finalist_fraction`` of the ``iterations``, then the lowest alone (1: the lowest
            alone right away, the race before 2026-11-25). A start that ends lowest is often second at step 60
            (``docs/soft-arms.md``).
        finalist_fraction: fraction of the ``iterations`` after which the lowest of the ``finalists`` goes on alone.
        seed: seed of the ``torch.Generator`` of the random hypotheses (``initial_control_points``).
        keypoint_mode: ``"mask"`` (mask term only), ``"endpoint"`` (mask + the tip), ``"keypoints"`` (mask +
            ``keypoints`` points evenly spaced along the arm, the last one the tip).
        keypoints: number of keypoints ``k`` in mode ``"keypoints"`` (at fractions ``j / k`` of the path length).
        working_max_side: the fit runs on the mask cropped around the robot and shrunk so that the crop's longest
            side is at most this (pixels); see ``observe_mask``. 480 since 2026-11-27 (was 320): on 60 two-section
            tuning arms 2.67 -> 2.41 px and 4.04 -> 3.79 mm, on 60 single-bend ones 1.97 -> 1.80 px, for 10-30 %
            more time (both cores / one thread) (``docs/soft-arms.md``); a video's fits too (at 640x360 the same as
            at 320, at 1280x720 better, ``docs/tracking.md``).
        sigma_px2: softness of the rendered silhouette, squared pixels of the working resolution (the cut-off is
            where an outside face's probability is 1e-4, ``SoftRasterSettings.from_sigma``).
        prefit_iterations: steps (``prefit_solver``) of a pre-fit without rendering, before the ``iterations``:
            every start's projected centreline is pulled onto ``SKELETON_POINTS`` points along the skeleton path
            (plus the length term) and its apparent width onto the mask's (``w_width``). Cheap (no rendering); 0
            skips it.
        prefit_solver: ``"adam"`` (default): the pre-fit is ``prefit_iterations`` Adam steps; ``"lm"``: at most
            ``prefit_iterations`` Levenberg-Marquardt steps (``prefit_levenberg_marquardt``; Bezier curves only),
            each about two loss evaluations, converged in 5-10 where Adam takes 100 steps: the warm fits' default
            (``pipeline.track``, ``docs/tracking.md``); the multi-start fit keeps Adam (no faster there, with its
            many hypotheses of several orders; on 20 two-section tuning arms 1.85 px / 4.86 mm against 2.01 /
            2.58).
        prefit_starts: hypotheses in the pre-fit (``initial_control_points``: its 6 deterministic ones, then random
            ones); the ``starts`` whose rendered loss is lowest after the pre-fit go on to the rendered fit (one
            render of all of them).
        warm_hypotheses: with a warm start (``reconstruct_shape``'s ``initial_control_points_cam_m``), also start
            from these of the mask's hypotheses (``initial_control_points``: 0 the per-point depths from the
            apparent widths, 1 their straight-line fit, 2 the opposite slope, 3 a constant depth, 4 and 5 the
            same as 0 and 1 with the taper at 3D arc length), in the same batch; the lowest loss wins. A warm
            start carries its depth profile from frame to frame and settles in a neighbouring basin of the loss; a
            fresh depth profile beside it lets a video's frames leave it (``docs/tracking.md``). ``()``: the warm
            start alone.
        warm_keep_start: with a warm start, the rendered fit also starts from the warm start as given (not
            pre-fitted), beside its pre-fitted self and the hypotheses: the pre-fit follows the motion, but its
            loss (the skeleton, not the silhouette) pulls a still-good estimate off the silhouette's minimum;
            the rendered loss then picks (``docs/tracking.md``). The tracker's default. Nothing to keep without a
            pre-fit (``prefit_iterations=0``: the warm start goes on as it is anyway).
        warm_slow_start: with a warm start, > 0 also starts the pre-fitted warm start a second time at this
            fraction of the rate (``ParamGroup.start_rates``), last, in the same batch; 0 (default): not. Adam's
            first steps move every coordinate by about the full rate and throw a close warm start out of its
            basin; the slow copy stays near it while the others follow fast motion, and the lowest loss wins
            (``docs/tracking.md``).
        multi_start_fraction: fraction of the ``iterations`` run with all starts in one batch; the ``finalists``
            of lowest loss then go on (and of each further order's ``order_iterations``, after which the lowest
            goes on alone). 1 runs every start to the end.
        render_rings, render_angles: tube mesh rendered during the fit (rings evenly spaced in the Bezier
            parameter, vertices per ring). The radius profile (``robot.n_rings`` values, linear taper in *arc
            length* plus offsets) is interpolated to each ring's arc-length fraction; the ring polygon is scaled so
            that its mean projected width equals the circle's, and shrunk by ``soft_edge_offset_px`` at its apparent radius.
            16 rings since 2026-12-07 (32 before): the same errors on the tuning arms and videos for 12-20 % less
            time (``docs/soft-arms.md``).
        lr_control: Adam rate of the control points, as a fraction of the arm length per step (the state is each
            control point's ray and log depth, see ``control_points_to_state``; the rate in those units is this
            times the length over the initial mean depth).
        lr_radius: Adam rate of the radius offsets, as a fraction of the base radius per step (0 freezes them).
        final_lr_factor: both rates decay geometrically to this fraction of themselves at the last step.
        w_mask: weight of the mask term (mismatch as a fraction of the mask area).
        w_keypoint: weight of the keypoint term (mean keypoint distance as a fraction of the path length).
        w_length: weight of the length term ``((l - L) / L)^2`` (``l`` the centreline's length, ``L`` the robot's):
            the known length fixes the arm's depth, which the silhouette alone barely does. 0 gives the paper's
            loss.
        w_width: weight of the pre-fit's width term: the mean over the middle 80 % of the path, weighted by
            ``r_px^2``, of ``(r_model / r_px - 1)^2``, the model's apparent radius (half its projected ring's extent
            across the centreline) against the mask's.
        radius_tolerance: the radii stay within this fraction of the known taper (0.2: 80 % to 120 %).
        rim_offset_px: how far the mask's outline lies outside the arm's true outline, pixels of the full image
            (positive: the segmenter's masks are too wide, by a dilation; negative: too narrow). The fit reads the
            arm's depth from its apparent width, so a rim 1 px off costs about 10-20 mm at 0.4 m
            (``docs/soft-arms.md``, "A known rim offset"); given it, the hypotheses take their depths from the
            widths less it and the rendered tube is drawn that much wider than the arm. 0 (default): the mask is
            taken as exact. Measure it on a few frames with true masks: ``(segmented area - true area) /
            true outline length`` (``pipeline.evaluate.rim_offset_px``). ``"auto"``: not known; after the fit
            (as with 0), 0 and each of ``RIM_SEARCH_PX`` are tried by a short refit from the answer (its depth
            scaled by the width the offset takes off), and an offset is kept when its loss is more than
            ``RIM_SEARCH_MARGIN`` below the refit's at 0 (``search_rim_offset``; ``ShapeResult.rim_offset_px``,
            ``rim_offset_losses``); about 1.5-1.8x the time, and on tuning arms it halves a 1-2 px rim's depth error
            where a known offset removes it. Bezier single-image fits only (no warm start); a video's tracker
            searches over its first frames together (``pipeline.track.ShapeTrackConfig.rim_search_frames``).
            ``"image"``: read from the colour image the mask was segmented from (``reconstruct_shape(...,
            image=...)``), on the component the fit keeps: ``pipeline.segment.image_rim_offset_px``, the centroid
            of the colour's step across the outline against the mask's own; ``ShapeResult.rim_offset_px`` says
            what it read. For a segmenter's masks (``shape --image`` does so by default).
        fit_both_ends: when the skeleton path's base end is disputed (``ShapeObservation.base_end_disputed``: the
            image border names one end, the apparent widths the other) and nothing else names it (no
            ``base_pixel``, no warm start, no held base), fit once with each end as the base and keep the lower
            score (the loss plus the order penalty); such a mask costs two fits. ``False``: the border's end only
            (the fit before 2026-11-25, ``docs/soft-arms.md``).
        progress: show a progress bar.
        compile: evaluate the Bezier fit's losses through ``torch.compile`` (inductor; needs a C++ compiler), on
            the tensor path (the graph cannot call the numba kernels): on CPU a warm frame is slower than the
            default's since 2026-12-07, whose losses run as compiled kernels (``FUSED_LOSS``; 0.20 against 0.13 s,
            ``docs/tracking.md``; 1.2x faster before, 2.2-2.6x before the curve frames and the mask loss moved to
            numba); the first fits of a process compile for tens of seconds (seconds with torch's disk cache warm),
            and a new working-image size may compile again. Not measured on CUDA. Where compiling fails the fit
            warns once and goes on uncompiled.
    """

    order: int | str = "auto"
    model: str = "auto"
    sections: int = 2
    section_lengths_m: tuple[float, ...] = ()
    pcc_start: str = "bezier"
    pcc_iterations: int = 50
    iterations: int = 200
    order_iterations: int = 100
    order_starts: int = 3
    order_hypotheses: int = 6
    order_warmup_iterations: int | None = None
    order_penalty: float = 0.002
    max_bend: float = 0.5
    starts: int = 8
    finalists: int = 2
    finalist_fraction: float = 0.5
    seed: int = 0
    keypoint_mode: str = "keypoints"
    keypoints: int = 4
    working_max_side: int = 480
    sigma_px2: float = 0.25
    prefit_iterations: int = 100
    prefit_starts: int = 18
    prefit_solver: str = "adam"
    warm_hypotheses: tuple[int, ...] = ()
    warm_keep_start: bool = False
    warm_slow_start: float = 0.0
    multi_start_fraction: float = 0.3
    render_rings: int = 16
    render_angles: int = 16
    lr_control: float = 0.01
    lr_radius: float = 0.0
    final_lr_factor: float = 0.1
    w_mask: float = 1.0
    w_keypoint: float = 0.3
    w_length: float = 10.0
    w_width: float = 1.0
    radius_tolerance: float = 0.2
    rim_offset_px: float | str = 0.0
    fit_both_ends: bool = True
    progress: bool = False
    compile: bool = False

    def __post_init__(self) -> None:
        if self.order != "auto":
            if isinstance(self.order, str):
                raise ConfigError(f"order: expected 'auto' or an int >= 1, got {self.order!r}")
            _int_at_least(self.order, 1, "order")
        check_choice(self.model, MODELS, "model")
        _int_at_least(self.sections, 1, "sections")
        lengths = tuple(self.section_lengths_m)
        if lengths and (len(lengths) != self.sections or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                for v in lengths)):
            raise ConfigError(f"section_lengths_m: expected {self.sections} lengths > 0 (metres, one per section) or "
                              f"none (fitted), got {self.section_lengths_m!r}")
        object.__setattr__(self, "section_lengths_m", tuple(float(v) for v in lengths))
        check_choice(self.pcc_start, PCC_STARTS, "pcc_start")
        _int_at_least(self.pcc_iterations, 1, "pcc_iterations")
        _int_at_least(self.iterations, 1, "iterations")
        _int_at_least(self.order_iterations, 1, "order_iterations")
        _int_at_least(self.order_starts, 1, "order_starts")
        _int_at_least(self.order_hypotheses, 1, "order_hypotheses")
        warmup = self.order_warmup_iterations
        if warmup is not None and (isinstance(warmup, bool) or not isinstance(warmup, int) or warmup < 0):
            raise ConfigError(f"order_warmup_iterations: expected an int >= 0 or None (as many as the first order's "
                              f"starts ran together), got {warmup!r}")
        check_positive(self.order_penalty, "order_penalty", allow_zero=True)
        check_positive(self.max_bend, "max_bend", allow_zero=True)
        _int_at_least(self.starts, 1, "starts")
        _int_at_least(self.finalists, 1, "finalists")
        if not 0.0 < float(self.finalist_fraction) <= 1.0:
            raise ConfigError(f"finalist_fraction: expected a number in (0, 1], got {self.finalist_fraction!r}")
        _int_at_least(self.prefit_iterations, 0, "prefit_iterations")
        _int_at_least(self.prefit_starts, 1, "prefit_starts")
        check_choice(self.prefit_solver, PREFIT_SOLVERS, "prefit_solver")
        if self.model == "auto" and self.pcc_start != "bezier":
            raise ConfigError(f"pcc_start: model 'auto' refines the Bezier fit into sections, expected 'bezier', got "
                              f"{self.pcc_start!r}")
        if self.prefit_solver == "lm" and self.model == "pcc":
            raise ConfigError("prefit_solver: 'lm' pre-fits Bezier curves; use 'adam' with model='pcc'")
        hypotheses = tuple(self.warm_hypotheses)
        if not all(isinstance(h, int) and not isinstance(h, bool) and h >= 0 for h in hypotheses):
            raise ConfigError(f"warm_hypotheses: expected indices >= 0 of initial_control_points' hypotheses (0: "
                              f"per-point depths, 1: their line, 2: the opposite slope, 3: constant depth, 4 and 5: "
                              f"0 and 1 with the taper at 3D arc length), got {self.warm_hypotheses!r}")
        object.__setattr__(self, "warm_hypotheses", hypotheses)
        check_positive(self.warm_slow_start, "warm_slow_start", allow_zero=True)
        _int_at_least(self.seed, 0, "seed")
        check_choice(self.keypoint_mode, KEYPOINT_MODES, "keypoint_mode")
        _int_at_least(self.keypoints, 1, "keypoints")
        _int_at_least(self.working_max_side, 16, "working_max_side")
        if not 0.0 < float(self.multi_start_fraction) <= 1.0:
            raise ConfigError(
                f"multi_start_fraction: expected a number in (0, 1], got {self.multi_start_fraction!r}"
            )
        _int_at_least(self.render_rings, 2, "render_rings")
        _int_at_least(self.render_angles, 3, "render_angles")
        check_positive(self.sigma_px2, "sigma_px2")
        check_positive(self.lr_control, "lr_control")
        check_positive(self.lr_radius, "lr_radius", allow_zero=True)
        check_positive(self.final_lr_factor, "final_lr_factor")
        check_positive(self.w_mask, "w_mask", allow_zero=True)
        check_positive(self.w_keypoint, "w_keypoint", allow_zero=True)
        check_positive(self.w_length, "w_length", allow_zero=True)
        check_positive(self.w_width, "w_width", allow_zero=True)
        if not 0.0 <= float(self.radius_tolerance) < 1.0:
            raise ConfigError(f"radius_tolerance: expected a number in [0, 1), got {self.radius_tolerance!r}")
        if self.rim_offset_px not in ("auto", "image") and (
                isinstance(self.rim_offset_px, bool) or not isinstance(self.rim_offset_px, (int, float))
                or not math.isfinite(self.rim_offset_px)):
            raise ConfigError(f"rim_offset_px: expected a finite number (pixels; positive: the mask is too wide), "
                              f"'auto' or 'image', got {self.rim_offset_px!r}")
        if self.rim_offset_px == "auto" and self.model == "pcc":
            raise ConfigError("rim_offset_px: 'auto' searches with Bezier refits; give a number with model='pcc' (or "
                              "use model 'auto': the offset searched with the Bezier fit, the sections refined at it)")

    @property
    def orders(self) -> tuple[int, ...]:
        """The Bezier orders fitted, in turn: ``AUTO_ORDERS`` for ``"auto"``, else ``(order,)``."""
        return AUTO_ORDERS if self.order == "auto" else (self.order,)

    @property
    def known_rim_offset_px(self) -> float:
        """The rim offset the fit takes as known: ``rim_offset_px``, 0 for ``"auto"`` (searched after the fit)
        and for ``"image"`` (``reconstruct_shape`` replaces it by the number it reads before fitting)."""
        return 0.0 if self.rim_offset_px in ("auto", "image") else float(self.rim_offset_px)

    @property
    def keypoint_count(self) -> int:
        """Keypoints used by ``keypoint_mode``: 0, 1 (the tip) or ``keypoints``."""
        return {"mask": 0, "endpoint": 1, "keypoints": self.keypoints}[self.keypoint_mode]


@dataclass(frozen=True, kw_only=True)
class ShapeObservation:
    """What the fit sees of the mask, at the working resolution (pixels of the undistorted, shrunk image).

    Fields:
        mask: ``(h, w)`` bool, cleaned (largest component, small holes filled).
        coverage: ``(h, w)`` float32 in [0, 1]: the fraction of each working pixel covered by the full-resolution
            mask (area average), zero away from the kept component; the mask term's target.
        camera: distortion-free camera of that image.
        path_px: ``(P, 2)`` skeleton path ``(u, v)`` from base to tip, extended to the mask boundary.
        radius_px: ``(P,)`` apparent radius of the arm along the path, pixels: half the coverage integrated
            across the path (see ``_apparent_radius``), less ``rim_offset_px`` (at least a fifth of it).
        keypoints_px: ``(K, 2)`` observed keypoints ``(u, v)``; ``K = 0`` in mode ``"mask"``.
        keypoint_fractions: ``(K,)`` their fractions of the path length, in (0, 1].
        scale: ``(sx, sy)`` working over full-resolution size.
        offset_px: ``(x0, y0)`` full-resolution pixel of the crop's corner: ``u = (u_w + 0.5) / sx - 0.5 + x0``.
        image_bounds_px: ``(u_min, v_min, u_max, v_max)``: the whole image's edges in working pixels (the crop
            may end inside the image; the arm only ends where the image does).
        cut_ends: ``(base, tip)``: whether that end of the path lies within 1.5 working px of the image border
            (the arm may continue outside the image).
        base_end_disputed: the base end was chosen by the image border (no ``base_pixel``, the ends not about as
            near the border, the base end not cut by it), yet the arm tapers (``taper_ratio >= 1.2``) and the
            path's last third is wider in the image than its first: the two rules disagree (e.g. an arm curling
            towards the camera, whose tip section runs through a wide blob).
        rim_offset_px: how far the mask's outline lies outside the arm's, working pixels
            (``ShapeFitConfig.rim_offset_px`` scaled).
    """

    mask: np.ndarray
    coverage: np.ndarray
    camera: Camera
    path_px: np.ndarray
    radius_px: np.ndarray
    keypoints_px: np.ndarray
    keypoint_fractions: np.ndarray
    scale: tuple[float, float]
    offset_px: tuple[int, int]
    image_bounds_px: tuple[float, float, float, float]
    cut_ends: tuple[bool, bool]
    base_end_disputed: bool = False
    rim_offset_px: float = 0.0

    @property
    def path_length_px(self) -> float:
        """Length of the skeleton path, working pixels."""
        return float(polyline_arc_length(self.path_px)[-1])

    def to_full_resolution(self, points_px: np.ndarray) -> np.ndarray:
        """``(N, 2)`` working-resolution pixels -> full-resolution pixels of the undistorted image."""
        (sx, sy), (x0, y0) = self.scale, self.offset_px
        return np.stack([(points_px[:, 0] + 0.5) / sx - 0.5 + x0, (points_px[:, 1] + 0.5) / sy - 0.5 + y0], axis=1)


@dataclass(frozen=True, kw_only=True)
class ShapeResult:
    """Outcome of :func:`reconstruct_shape`, all in the undistorted camera frame / image at full resolution.

    Fields:
        control_points_cam_m: ``(n+1, 3)`` Bezier control points, camera frame, metres, base first; with
            ``model="pcc"`` the ``N + 1`` section end points (base, the joints between sections, tip).
        radii_m: ``(n_rings,)`` tube radius at fractions ``j / (n_rings - 1)`` of the arc length from the base,
            metres (the known taper plus the fitted offsets).
        centerline_cam_m: ``(101, 3)`` centreline points uniform in arc length, base to tip, metres.
        order: the Bezier order ``n`` of the result (``ShapeFitConfig.order``, or the one ``"auto"`` chose); with
            ``model="pcc"`` the number of sections ``N`` (``control_points_cam_m`` has ``order + 1`` rows).
        order_losses: best loss of every order fitted (one entry unless ``order="auto"``; the search stops at the
            first order that does not lower the score), the chosen one's is ``loss``.
        order_control_points: every order's best control points ``(n+1, 3)`` (camera frame, metres).
        keypoints_px: ``(K, 2)`` observed keypoints used by the fit ``(u, v)``, full-resolution pixels.
        keypoint_fractions: ``(K,)`` their fractions of the skeleton path length.
        skeleton_px: ``(P, 2)`` the skeleton path ``(u, v)`` base to tip, full-resolution pixels.
        loss: best loss (dimensionless, see the module docstring).
        start_losses: ``(S,)`` best loss of each start while all starts ran (``multi_start_fraction``).
        best_start: index of the start kept.
        history: ``(N, S)`` loss of every start at every iteration; once the best start goes on alone only its
            column is filled (NaN elsewhere); with ``order="auto"`` the further orders' steps follow, in that column
            (the lowest loss of the order's starts at each step; first the fresh starts' warm-up steps alone). With
            ``model="pcc"`` from the Bezier answer (``pcc_start="bezier"``): ``(N, 1)``, the Bezier fit's lowest
            loss at each of its steps, then the sections' refinement.
        iterations: N (``iterations`` plus ``order_warmup_iterations`` (when ``order_starts > 1``) and
            ``order_iterations`` per further order; plus ``pcc_iterations`` with ``model="pcc"`` from the Bezier
            answer).
        keypoint_mode: the loss variant used.
        camera: the distortion-free full-resolution camera the results refer to.
        working_size: ``(h, w)`` of the fit.
        preprocess_seconds, prefit_seconds, fit_seconds, seconds: wall time of the observation, initialisation
            and set-up; of the pre-fit (with ``order="auto"`` every further order's fresh hypotheses' too, pre-fitted
            with the first order's since 2026-11-25; they were counted in ``fit_seconds`` before); of the rendered
            fit; in all.
        model: ``"bezier"`` or ``"pcc"`` (``ShapeFitConfig.model``; with ``"auto"`` the one kept, whose fields
            these are, but ``seconds`` counts both fits).
        model_losses: with ``ShapeFitConfig.model="auto"``, the loss of each model fitted (``{"bezier": ...,
            "pcc": ...}``; the lower is ``loss``), else empty.
        pcc: with ``model="pcc"`` the fitted sections (:class:`PccParameters`); ``None`` for a Bezier result.
        base_end_disputed: the image border and the apparent widths named different ends of the skeleton path as
            the base (``ShapeObservation.base_end_disputed``).
        other_end_loss: when it was disputed and ``ShapeFitConfig.fit_both_ends``, the loss of the fit with the
            other end as the base (the one not kept; both fits' time is in ``seconds``), else ``None``.
        rim_offset_px: the rim offset the result was fitted with (``ShapeFitConfig.rim_offset_px``; with
            ``"auto"`` the one the search kept, 0 when none was lower by the margin), full-image pixels.
        rim_offset_losses: with ``"auto"``, the loss of the refit at each offset tried (0 included), else empty.
        arm_candidates: how many components of the mask were candidates for the arm (``ARM_CANDIDATE_FRACTION`` of
            the largest's area or more; 1: the mask had one); with more, the fit used the one the arm's pre-fit
            explains best (``choose_arm_component``), and ``arm_candidate_losses`` holds their
            pre-fit losses, largest component first (``inf``, JSON ``null``, for one without a skeleton path).
        moments: Adam's state of the answer's start after the rendered fit that gave it (parameter group ->
            :class:`pipeline.optimize.AdamMoments`), for a warm fit of a video's next frame to begin with
            (``reconstruct_shape(initial_moments=...)``, ``pipeline.track``); ``None`` for sections
            (``model="pcc"``). Not in the JSON.
    """

    control_points_cam_m: np.ndarray
    radii_m: np.ndarray
    centerline_cam_m: np.ndarray
    order: int
    order_losses: dict[int, float]
    order_control_points: dict[int, np.ndarray]
    keypoints_px: np.ndarray
    keypoint_fractions: np.ndarray
    skeleton_px: np.ndarray
    loss: float
    start_losses: np.ndarray
    best_start: int
    history: np.ndarray
    iterations: int
    keypoint_mode: str
    camera: Camera
    working_size: tuple[int, int]
    preprocess_seconds: float
    prefit_seconds: float
    fit_seconds: float
    seconds: float
    model: str = "bezier"
    model_losses: dict[str, float] = dataclasses.field(default_factory=dict)
    pcc: PccParameters | None = None
    base_end_disputed: bool = False
    other_end_loss: float | None = None
    rim_offset_px: float = 0.0
    rim_offset_losses: dict[float, float] = dataclasses.field(default_factory=dict)
    arm_candidates: int = 1
    arm_candidate_losses: tuple[float, ...] = ()
    moments: dict[str, AdamMoments] | None = dataclasses.field(default=None, repr=False, compare=False)

    @property
    def image_size(self) -> tuple[int, int]:
        """``(H, W)`` of the input mask."""
        return self.camera.image_size

    def to_dict(self) -> dict:
        """The result file's content (``pipeline shape --out``); arrays as nested lists."""
        return {
            "model": self.model,
            "model_losses": dict(self.model_losses),
            **({"pcc": self.pcc.to_dict()} if self.pcc is not None else {}),
            "control_points_cam_m": self.control_points_cam_m,
            "radii_m": self.radii_m,
            "centerline_cam_m": self.centerline_cam_m,
            "order": self.order,
            "order_losses": {str(n): value for n, value in self.order_losses.items()},
            "order_control_points_cam_m": {str(n): value for n, value in self.order_control_points.items()},
            "loss": self.loss,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "preprocess_seconds": self.preprocess_seconds,
            "prefit_seconds": self.prefit_seconds,
            "fit_seconds": self.fit_seconds,
            "keypoint_mode": self.keypoint_mode,
            "keypoints_px": self.keypoints_px,
            "keypoint_fractions": self.keypoint_fractions,
            "start_losses": self.start_losses,
            "best_start": self.best_start,
            "camera": self.camera.to_dict(),
            "image_size": {"width": self.camera.width, "height": self.camera.height},
            "working_size": {"width": self.working_size[1], "height": self.working_size[0]},
            "base_end_disputed": self.base_end_disputed,
            "other_end_loss": self.other_end_loss,
            "rim_offset_px": self.rim_offset_px,
            "rim_offset_losses": {repr(float(c)): value for c, value in self.rim_offset_losses.items()},
            "arm_candidates": self.arm_candidates,
            "arm_candidate_losses": list(self.arm_candidate_losses),
        }


def observe_mask(
    mask: np.ndarray,
    camera: Camera,
    *,
    max_side: int,
    keypoints: int,
    base_pixel: tuple[float, float] | None = None,
    taper_ratio: float = 1.0,
    rim_offset_px: float = 0.0,
) -> ShapeObservation:
    """Undistort, crop, shrink and clean the mask; extract the skeleton path, its apparent radius, the keypoints.

    The working image is the undistorted mask's largest component, cropped to its bounding box plus a margin of
    ``CROP_MARGIN`` of its size (and 8 px) on each side, shrunk so that its longest side is at most
    ``max_side``: a small arm in a large image keeps its detail.

    Args:
        mask: ``(H, W)`` bool robot mask at the camera's resolution (as taken, i.e. distorted).
        camera: the camera that took it (``(H, W)`` must be its size).
        max_side: the crop is shrunk so that its longest side is at most this (pixels).
        keypoints: number ``k`` of keypoints, at fractions ``j / k`` of the path length (0: none; 1: the tip).
        base_pixel: ``(u, v)`` of the arm's base in the full-resolution image, or ``None`` meaning *unknown*: the
            path end nearer the image border is the base (arms enter the image from its edge); when both ends
            are about as near (within 5 % of the shorter image side) and ``taper_ratio >= 1.2``, the thicker end.
        taper_ratio: base radius over tip radius of the arm.
        rim_offset_px: how far the mask's outline lies outside the arm's, full-resolution pixels
            (``ShapeFitConfig.rim_offset_px``): taken off the apparent radii.

    Raises:
        ShapeError: ``mask is empty``, or the skeleton has no path.
        ConfigError: the camera does not match the mask size.
    """
    full = _undistorted_arm(mask, camera)
    return _observe(full, camera, _crop_box(full), max_side=max_side, keypoints=keypoints, base_pixel=base_pixel,
                    taper_ratio=taper_ratio, rim_offset_px=rim_offset_px)


def _undistorted_arm(mask: np.ndarray, camera: Camera) -> np.ndarray:
    """The mask undistorted, pieces cut apart by an occluder joined, the largest component kept: ``(H, W)`` bool.

    Raises:
        ShapeError: nothing is left after undistortion.
    """
    check_mask(mask)
    check_image_matches_camera(mask.shape, camera)
    undistorted, _ = undistort_image(mask, camera, is_mask=True)
    if not undistorted.any():
        raise ShapeError("mask is empty after undistortion: the robot lies outside the undistorted image")
    return clean_mask(join_pieces(undistorted))  # pieces cut apart by an occluder joined, then the largest kept


def _crop_box(*fulls: np.ndarray) -> tuple[int, int, int, int]:
    """``(x0, y0, x1, y1)``: the bounding box of the non-empty ``(H, W)`` masks together, plus ``CROP_MARGIN`` of
    its longest side and 8 px on each side, clipped to the image (``x1``, ``y1`` exclusive)."""
    union = fulls[0] if len(fulls) == 1 else np.logical_or.reduce(fulls)
    H, W = union.shape
    rows, cols = np.nonzero(union)
    size = max(int(cols.max() - cols.min()) + 1, int(rows.max() - rows.min()) + 1)
    margin = int(math.ceil(CROP_MARGIN * size)) + 8
    return (max(int(cols.min()) - margin, 0), max(int(rows.min()) - margin, 0),
            min(int(cols.max()) + margin + 1, W), min(int(rows.max()) + margin + 1, H))


def _observe(
    full: np.ndarray,
    camera: Camera,
    box: tuple[int, int, int, int],
    *,
    max_side: int,
    keypoints: int,
    base_pixel: tuple[float, float] | None,
    taper_ratio: float,
    rim_offset_px: float = 0.0,
) -> ShapeObservation:
    """:func:`observe_mask` of the undistorted, cleaned mask ``full`` (``_undistorted_arm``) in the crop ``box``
    (``_crop_box``: frames fitted together share one crop, hence one working camera)."""
    H, W = full.shape
    x0, y0, x1, y1 = box
    crop_K = ((camera.fx, 0.0, camera.cx - x0), (0.0, camera.fy, camera.cy - y0), (0.0, 0.0, 1.0))
    camera_w = working_camera(Camera(K=crop_K, width=x1 - x0, height=y1 - y0), max_side)
    crop = full[y0:y1, x0:x1]
    small = resize_image(crop, camera_w.image_size, is_mask=True)
    if not small.any():
        raise ShapeError(
            f"mask is empty at the working resolution {camera_w.width}x{camera_w.height}: the robot covers too "
            f"few pixels; raise working_max_side"
        )
    small = clean_mask(small)
    # Coverage of each working pixel by the full-resolution mask (an anti-aliased target that keeps the
    # sub-pixel edge positions), restricted to the kept component and its 1-pixel rim.
    coverage = resize_image(crop.astype(np.float32), camera_w.image_size, is_mask=False)
    coverage = coverage * cv2.dilate(small.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    sx, sy = camera_w.width / (x1 - x0), camera_w.height / (y1 - y0)
    bounds = (-x0 * sx - 0.5, -y0 * sy - 0.5, (W - x0) * sx - 0.5, (H - y0) * sy - 0.5)  # the image, working px
    base_w = None
    if base_pixel is not None:
        base = np.asarray(base_pixel, dtype=np.float64)
        if base.shape != (2,) or not np.isfinite(base).all():
            raise ConfigError(f"base_pixel: expected (u, v), two finite numbers, got {base_pixel!r}")
        base_w = ((base[0] - x0 + 0.5) * sx - 0.5, (base[1] - y0 + 0.5) * sy - 0.5)
    path = skeleton_path(small, base_w if base_w is not None else (0.0, 0.0))
    if polyline_arc_length(path)[-1] <= 0:
        raise ShapeError("mask skeleton has no path: its skeleton is a single point")
    rim_w = float(rim_offset_px) * math.sqrt(sx * sy)
    radius = _apparent_radius(coverage, small, path)
    radius = np.maximum(radius - rim_w, 0.2 * radius)  # the arm's, not the mask's
    # Distance of each path end to the image border, in working pixels.
    border = [min(u - bounds[0], v - bounds[1], bounds[2] - u, bounds[3] - v) for u, v in (path[0], path[-1])]
    disputed = False
    if base_w is None:
        third = max(len(path) // 3, 1)
        undecided = abs(border[0] - border[1]) < 0.05 * min(H * sy, W * sx)
        if (radius[-third:].mean() > radius[:third].mean()) if undecided and taper_ratio >= 1.2 else \
                border[1] < border[0]:
            path, radius, border = path[::-1].copy(), radius[::-1].copy(), border[::-1]
        disputed = (not undecided and taper_ratio >= 1.2 and border[0] >= 1.5
                    and bool(radius[-third:].mean() > radius[:third].mean()))
    if keypoints == 0:
        points, fractions = np.zeros((0, 2)), np.zeros(0)
    else:
        points, fractions = arc_length_keypoints(path, keypoints)
    return ShapeObservation(mask=small, coverage=coverage, camera=camera_w, path_px=path,
                            radius_px=radius.astype(np.float64), keypoints_px=points, keypoint_fractions=fractions,
                            scale=(sx, sy), offset_px=(x0, y0), image_bounds_px=bounds,
                            cut_ends=(border[0] < 1.5, border[1] < 1.5), base_end_disputed=disputed,
                            rim_offset_px=rim_w)


def initial_control_points(
    observation: ShapeObservation,
    robot: ContinuumRobot,
    starts: int,
    generator: torch.Generator,
    *,
    order: int,
    only: Sequence[int] | None = None,
) -> torch.Tensor:
    """Control points of ``starts`` hypotheses, all inside the camera frustum, from what the mask shows.

    The skeleton path is back-projected along its pixels' rays at a depth profile ``z(s)`` over the path fraction
    ``s``; the Bezier control points are the least-squares fit (Bezier parameter = path fraction, refined to the
    nearest curve points) to those 3D points, scaled about the camera centre (which keeps their image) so that the
    curve is as long as the arm plus half the end radii (the path runs onto the end caps). When the path touches
    the image border (the arm is cut) the visible part may be shorter: then the scale only ever shrinks a curve
    longer than that.

    - Width: each path point's depth is ``f r(s) / r_px(s)`` (known taper radius over the apparent radius);
      ``a + b (s - 1/2)`` is its least-squares line over the middle 80 % of the path, weighted by ``r_px^2`` (a
      wide part's relative width is better known).
    - Starts: 0 takes the per-point depths themselves on the middle 80 % (the line near the ends, where the caps
      are), 1 the line, 2 the opposite slope (the tip nearer instead of farther), 3 a constant depth; 4 and 5 are
      0 and 1 with the taper taken at each point's fraction of the arm's *3D* arc length instead of the path's
      (solved with the depths in ``CONSISTENT_TAPER_ROUNDS`` rounds, the depths smoothed over 10 % of the path
      for the arc length; the Bezier parameters start at those fractions): where the arm runs towards or away
      from the camera its image is foreshortened and the path fraction puts the taper's radius in the wrong
      place; the others ``a + beta (s - 1/2) + gamma ((s - 1/2)^2 - 1/12)`` with ``beta`` uniform in
      ``[-0.6 a, 0.6 a]`` (a slope) and ``gamma`` in ``[-a, a]`` (a bend towards or away from the camera), the
      control points then moved by ``N(0, (1 % L)^2)``; drawn from ``generator``.

    Args:
        observation: from :func:`observe_mask`.
        robot: length and radii.
        starts: S (the first ``min(S, 6)`` are the deterministic ones above, in that order).
        generator: CPU ``torch.Generator`` for the random starts (drawn only from start 6 on).
        order: Bezier order ``n``.
        only: build only the starts of these indices (each in ``[0, S)``), in this order; each is the start the
            call without ``only`` gives (a skipped random start's draws are still taken). A warm fit needs one.

    Returns:
        ``(S, n+1, 3)`` float64 control points (``(len(only), n+1, 3)`` with ``only``), camera frame, metres, every
        control point at depth > 0.
    """
    wanted = list(range(starts)) if only is None else [int(i) for i in only]
    if not all(0 <= i < starts for i in wanted):
        raise ConfigError(f"only: expected start indices in [0, {starts}), got {list(only)}")
    path = observation.path_px
    cum = polyline_arc_length(path)
    frac = cum / cum[-1]  # (P,) fraction of the path length at each path point
    cam = observation.camera
    f = math.sqrt(cam.fx * cam.fy)
    rays = np.linalg.solve(cam.K_array(), np.concatenate([path, np.ones((len(path), 1))], axis=1).T).T  # (P, 3)
    middle = (frac >= 0.1) & (frac <= 0.9)
    if middle.sum() < 3:
        middle = np.ones_like(frac, dtype=bool)
    weight = observation.radius_px[middle] ** 2

    def depths(fractions: np.ndarray) -> tuple[np.ndarray, float, float]:
        """Per-point depths ``(P,)`` from the apparent width with the taper at arc-length ``fractions``, and the
        ``(a, b)`` of their weighted line over the middle of the path."""
        taper = robot.base_radius_m + (robot.tip_radius_m - robot.base_radius_m) * fractions  # (P,) metres
        depth = f * taper / observation.radius_px  # (P,) metres
        return depth, *_depth_line(fractions, depth, middle, weight)

    depth, a, b = depths(frac)
    if 4 in wanted or 5 in wanted:
        frac_3d = consistent_taper_fractions(rays, cum, middle, weight, lambda fractions: depths(fractions)[0])
        depth_3d, a_3d, b_3d = depths(frac_3d)
    a = a if a > 0 else float(np.median(depth[middle]))
    target = robot.length_m + 0.25 * (robot.base_radius_m + robot.tip_radius_m)
    cut = any(observation.cut_ends)
    built = {}
    dense = torch.linspace(0.0, 1.0, 201, dtype=torch.float64)
    for i in range(max(wanted, default=-1) + 1):
        if i not in wanted:
            if i >= 6:  # the draws of a random start, so that the later ones are the same
                torch.rand(2, generator=generator, dtype=torch.float64)
                torch.randn((order + 1, 3), generator=generator, dtype=torch.float64)
            continue
        noise = 0.0
        parameters = frac  # Bezier parameters of the back-projected points: the path fraction
        if i == 0:
            z = np.where(middle, depth, a + b * (frac - 0.5))
        elif i in (4, 5):  # the 3D arc-length taper's per-point depths and line, at their own fractions
            parameters = frac_3d
            line = a_3d + b_3d * (frac_3d - 0.5)
            z = np.where(middle, depth_3d, line) if i == 4 else line
        else:
            bend = 0.0
            if i < 4:
                slope = (float(b), -float(b), 0.0)[i - 1]
            else:
                slope, bend = (a * (2.0 * float(v) - 1.0) * m
                               for v, m in zip(torch.rand(2, generator=generator, dtype=torch.float64), (0.6, 1.0)))
                noise = 0.01 * robot.length_m
            z = a + slope * (frac - 0.5) + bend * ((frac - 0.5) ** 2 - 1.0 / 12.0)
        points = rays * np.maximum(z, 0.2 * a)[:, None]  # (P, 3)
        control = _fit_bezier(points, parameters, order)  # (n+1, 3)
        length = float(polyline_arc_length(bezier_points(torch.from_numpy(control)[None], dense)[0].numpy())[-1])
        control = control * (target / length if not cut else min(1.0, target / length))
        if noise:
            control = control + noise * torch.randn(control.shape, generator=generator, dtype=torch.float64).numpy()
        control[:, 2] = np.maximum(control[:, 2], 0.1 * a)
        built[i] = control
    return torch.from_numpy(np.stack([built[i] for i in wanted]) if wanted else np.empty((0, order + 1, 3)))


def reconstruct_shape(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig = ShapeFitConfig(),
    *,
    base_pixel: tuple[float, float] | None = None,
    initial_control_points_cam_m: np.ndarray | None = None,
    fixed_base_cam_m: np.ndarray | None = None,
    image: np.ndarray | None = None,
    initial_moments: Mapping[str, AdamMoments] | None = None,
) -> ShapeResult:
    """Fit the robot's centreline (Bezier control points) and radii to one binary mask.

    Args:
        mask: ``(H, W)`` bool robot mask, as taken by ``camera`` (distortion is removed here).
        robot: length, base and tip radii, mesh (``ContinuumRobot``); a known base point or
            direction in ``robot`` is not used yet.
        camera: intrinsics and distortion at ``(H, W)``.
        config: fit settings (see ``ShapeFitConfig``).
        base_pixel: ``(u, v)`` of the base in the image, or ``None`` meaning *unknown* (the path end nearer the
            image border is taken as the base).
        initial_control_points_cam_m: ``(n+1, 3)`` control points (undistorted camera frame, metres, base first,
            every depth > 0) to start from, e.g. the previous frame's estimate in a video (``pipeline.track``),
            or ``None`` meaning *none*: the hypotheses are built from the mask (``initial_control_points``).
            When given, the fit starts from it, and from ``config.warm_hypotheses`` beside it (``config.starts``
            and ``config.prefit_starts`` are not used; the pre-fit still runs when ``config.prefit_iterations >
            0``).
        fixed_base_cam_m: ``(2, 3)`` = (base point, base direction) in the undistorted camera frame, metres and a
            unit vector, to hold: the curve's first control point is the base point and its second lies on the ray
            from it along the direction (only its distance along it is fitted), e.g. a soft arm's base found on a
            video's first frame (``pipeline.track``); or ``None`` meaning *free*.
        image: ``(H, W, 3)`` uint8 BGR, the image ``mask`` was segmented from (as taken by ``camera``), for
            ``config.rim_offset_px="image"``; ``None`` meaning *none* (not used otherwise).
        initial_moments: with ``initial_control_points_cam_m``, Adam's state to begin the rendered fit's starts
            with (the last frame's ``ShapeResult.moments``: each start's first steps then follow the step sizes and
            the motion the last fit ended with; ``pipeline.track`` passes them), or ``None`` meaning Adam's zeros.

    Returns:
        ShapeResult in the undistorted camera frame and image.

    Raises:
        ShapeError: empty mask, or a mask whose skeleton has no path.
        ConfigError: camera / mask size mismatch, bad settings, ``rim_offset_px="image"`` without an image.
    """
    if config.rim_offset_px == "image" and image is None:
        raise ConfigError("rim_offset_px: 'image' reads the rim from the image the mask was segmented from; pass "
                          "image=... (or give the offset as a number)")
    initial = None if initial_control_points_cam_m is None else _checked_start(initial_control_points_cam_m)
    base = None if fixed_base_cam_m is None else _checked_base(fixed_base_cam_m)
    if initial_moments is not None and initial is None:
        raise ConfigError("initial_moments: Adam's state carries a warm fit on; give initial_control_points_cam_m "
                          "too (or no moments)")
    if config.model != "bezier":
        if initial is not None or base is not None:
            raise ConfigError(f"initial_control_points_cam_m / fixed_base_cam_m: a warm start or a held base needs "
                              f"model 'bezier' (the {config.model} model starts from the mask only)")
        if config.section_lengths_m and abs(sum(config.section_lengths_m) - robot.length_m) > 0.01 * robot.length_m:
            raise ConfigError(f"section_lengths_m: they sum to {sum(config.section_lengths_m):.4g} m, expected the "
                              f"robot's length {robot.length_m:.4g} m (within 1 %)")
    candidate_losses: tuple[float, ...] = ()
    if initial is None:  # a mask with several large components: keep the one the arm's model explains best
        mask, candidate_losses = choose_arm_component(mask, robot, camera, config, base_pixel=base_pixel)
    if config.rim_offset_px == "image":  # read on the mask the fit uses, then taken as known
        check_mask(mask)
        if np.shape(image)[:2] != mask.shape:
            raise ConfigError(f"image: expected the mask's size {mask.shape}, got {np.shape(image)[:2]}")
        config = dataclasses.replace(config, rim_offset_px=image_rim_offset_px(image, mask))

    # model "auto" with rim_offset_px "auto": the offset is searched with the Bezier fit, its sections refined after
    rim_then_sections = config.model == "auto" and config.rim_offset_px == "auto"
    fit_config = dataclasses.replace(config, model="bezier") if rim_then_sections else config

    def fit_once(pixel: tuple[float, float] | None) -> ShapeResult:
        if fit_config.model == "pcc":
            return _reconstruct_pcc(mask, robot, camera, fit_config, pixel)
        if fit_config.model == "auto":
            return _reconstruct_lower(mask, robot, camera, fit_config, pixel)
        return _reconstruct(mask, robot, camera, fit_config, pixel, initial, base, initial_moments)

    if config.rim_offset_px == "auto" and initial is not None:
        raise ConfigError("rim_offset_px: 'auto' is searched after a fit from the mask, not with a warm start; give "
                          "the number (e.g. the one a video's first fit found)")
    with single_torch_thread():  # see the module docstring (Threads)
        result = fit_once(base_pixel)
        if (config.fit_both_ends and result.base_end_disputed and base_pixel is None and initial is None
                and base is None):
            log.info("shape: the image border and the widths name different base ends; fitting the other end too")
            other = fit_once(tuple(float(v) for v in result.skeleton_px[-1]))  # the other end as the base
            kept, dropped = (other, result) if _score(other, config) < _score(result, config) else (result, other)
            result = dataclasses.replace(kept, base_end_disputed=True, other_end_loss=dropped.loss,
                                         seconds=result.seconds + other.seconds)
    candidates = {"arm_candidates": max(len(candidate_losses), 1), "arm_candidate_losses": candidate_losses}
    if config.rim_offset_px == "auto":
        searched = _rim_search(mask, robot, camera, fit_config, result, base)
        if rim_then_sections:  # the sections from the answer at the offset kept, observed from the end it used
            sections = refine_pcc(mask, robot, camera, _sections_config(config, rim_offset_px=searched.rim_offset_px),
                                  searched, base_pixel=tuple(float(v) for v in searched.skeleton_px[0]))
            searched = _lower_loss(searched, dataclasses.replace(
                sections, rim_offset_px=searched.rim_offset_px, rim_offset_losses=searched.rim_offset_losses,
                base_end_disputed=searched.base_end_disputed, other_end_loss=searched.other_end_loss),
                seconds=searched.seconds + sections.seconds)
        return dataclasses.replace(searched, **candidates)
    return dataclasses.replace(result, rim_offset_px=config.known_rim_offset_px, **candidates)


#: Components of a mask with at least this fraction of the largest one's area are candidates for the arm.
ARM_CANDIDATE_FRACTION = 0.1


def choose_arm_component(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig = ShapeFitConfig(),
    *,
    base_pixel: tuple[float, float] | None = None,
) -> tuple[np.ndarray, tuple[float, ...]]:
    """The mask without the components that are larger than the arm's, when it has several large ones.

    A segmenter may mark clutter as well as the arm (the shipped network, on a tuning image, a red ellipse three times
    the arm's area, as confidently as the arm), and the fit keeps the largest component. Here the 8-connected
    components, pieces of an arm cut by an occluder grouped as one (``_arm_candidates``), of at least
    ``ARM_CANDIDATE_FRACTION`` of the largest's area are each scored alone by the pre-fit (``_prefit_loss``: how
    well a tube of the arm's length and taper follows its skeleton and widths; no rendering, about 0.5 s each); when
    the lowest loss is not the largest candidate's, the candidates larger than the chosen one are removed, so that
    it becomes the largest (the smaller pieces stay for ``join_pieces``). A mask of one large candidate comes back
    as it is, without scoring.

    Returns:
        ``(mask, losses)``: the mask the fit should use (``(H, W)`` bool, the input itself when unchanged) and the
        candidates' pre-fit losses, largest first (empty when there was one candidate).
    """
    check_mask(mask)
    if one_piece(mask):
        return mask, ()
    labels, candidates = _arm_candidates(mask)
    if len(candidates) <= 1:
        return mask, ()
    losses = []
    with single_torch_thread():  # as the fit (module docstring, Threads)
        for group in candidates:
            try:
                losses.append(_prefit_loss(np.isin(labels, group), robot, camera, config, base_pixel))
            except ShapeError:  # e.g. no skeleton path: not the arm
                losses.append(math.inf)
    best = int(np.argmin(losses))
    log.info("shape: %d large mask components, pre-fit losses %s; using the %s", len(candidates),
             ", ".join(f"{v:.4g}" for v in losses), "largest" if best == 0 else f"{best + 1}. largest")
    if best == 0:
        return mask, tuple(losses)
    larger = [label for group in candidates[:best] for label in group]
    return mask & ~np.isin(labels, larger), tuple(losses)  # the candidates larger than the chosen one


#: Margin (pixels) around the last estimate's projected tube in which ``follow_arm_component`` counts a component.
FOLLOW_MARGIN_PX = 4.0


def follow_arm_component(mask: np.ndarray, previous: ShapeResult, camera: Camera) -> np.ndarray:
    """The mask without the large components larger than the one the arm's last estimate overlaps most.

    For a video's warm-started frames (``pipeline.track``): where a segmenter marks clutter as well as the arm,
    the arm is the component where it was a frame ago, not the largest (``choose_arm_component`` chooses without
    an estimate, by the pre-fit). Candidates are the 8-connected components, pieces of an arm cut by an occluder
    grouped as one (``_arm_candidates``), of at least ``ARM_CANDIDATE_FRACTION`` of the largest's area; each is
    scored by its pixels inside ``previous``'s tube as ``camera`` sees it (the
    centreline's 101 points, each a disc of its projected radius plus ``FOLLOW_MARGIN_PX``). When the best is not
    the largest, the candidates larger than it are removed, so that it becomes the largest (the smaller pieces
    stay for ``join_pieces``, as ``choose_arm_component`` leaves them). A mask of one large component, or one that
    the estimate does not overlap at all (the arm moved far), comes back as it is.

    Args:
        mask: ``(H, W)`` bool, as taken by ``camera`` (distorted when it has distortion).
        previous: the last estimate (its ``centerline_cam_m`` and ``radii_m``, undistorted camera frame).
        camera: the camera the mask was taken with (its image size and distortion).

    Returns:
        ``(H, W)`` bool: ``mask`` itself when unchanged.
    """
    check_mask(mask)
    if one_piece(mask):
        return mask
    labels, candidates = _arm_candidates(mask)
    if len(candidates) <= 1:
        return mask
    tube = _projected_tube(previous, camera, mask.shape)
    per_label = np.bincount(labels[tube], minlength=int(labels.max()) + 1)
    overlaps = [int(per_label[group].sum()) for group in candidates]
    best = int(np.argmax(overlaps))  # the first of equals: the larger
    if best == 0 or overlaps[best] == 0:
        return mask
    log.info("shape: %d large mask components, %s px of them on the last estimate; using the %d. largest",
             len(candidates), ", ".join(str(v) for v in overlaps), best + 1)
    return mask & ~np.isin(labels, [label for group in candidates[:best] for label in group])


#: ``_arm_candidates`` groups components of at least this fraction of the largest one's area whose facing ends'
#: widths (within this many radii of the thinner piece from their nearest pair) are within this ratio of each other
#: (and whose gap ``join_pieces`` would bridge).
GROUP_FRACTION = 0.02
GROUP_END_RADII = 3.0
GROUP_RADIUS_RATIO = 2.0


def _arm_candidates(mask: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """``(labels (H, W) int32, candidates)``: the mask's 8-connected components, grouped as pieces of one arm cut by
    an occluder, and the groups of at least ``ARM_CANDIDATE_FRACTION`` of the largest group's area, largest first
    (each a list of labels).

    Two components (each of at least ``GROUP_FRACTION`` of the largest's area) are one group when ``join_pieces``
    would bridge them (the gap at most 4 radii of the larger one, its largest inscribed radius) and the widths of
    their facing ends (``piece_ends``: the largest inscribed radius within ``GROUP_END_RADII`` radii of the thinner
    piece from the nearest pair) are within ``GROUP_RADIUS_RATIO`` of each other: the two sides of an occluder cut
    one tube at one width, however much the tube tapers from base to tip (compared by their largest radii, the
    pieces of a strongly tapered arm were two candidates), while a blob is far wider than the arm where they face.
    Smaller components are groups of their own.
    """
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if count <= 2:
        return labels, [[label] for label in range(1, count)]
    areas = stats[1:, cv2.CC_STAT_AREA].astype(np.int64)
    pieces = [1 + int(i) for i in np.nonzero(areas >= GROUP_FRACTION * areas.max())[0]]
    parent = {label: label for label in range(1, count)}

    def root(label: int) -> int:
        while parent[label] != label:
            label = parent[label]
        return label

    if len(pieces) > 1:
        radius, outside = {}, {}
        for label in pieces:  # each piece's largest inscribed radius, in its box (padded: the image edge is no edge)
            x, y, w, h = (int(v) for v in stats[label, :4])
            piece = np.pad((labels[y:y + h, x:x + w] == label).astype(np.uint8), 1)
            radius[label] = max(float(cv2.distanceTransform(piece, cv2.DIST_L2, 5).max()), 1.0)
        by_area = sorted(pieces, key=lambda label: -areas[label - 1])  # the larger piece of a pair is the main one
        for a_index, a in enumerate(by_area):
            for b in by_area[a_index + 1:]:
                if a not in outside:  # full-image passes, once per piece that is a pair's main one
                    outside[a] = cv2.distanceTransform((labels != a).astype(np.uint8), cv2.DIST_L2, 5)
                ends = piece_ends(labels == a, labels == b, outside[a],
                                  near_px=GROUP_END_RADII * min(radius[a], radius[b]))
                if ends is not None and max(ends[2]) <= GROUP_RADIUS_RATIO * min(ends[2]):
                    parent[root(b)] = root(a)
    groups: dict[int, list[int]] = {}
    for label in range(1, count):
        groups.setdefault(root(label), []).append(label)
    area = {key: int(areas[np.array(members) - 1].sum()) for key, members in groups.items()}
    ranked = sorted(groups, key=lambda key: (-area[key], min(groups[key])))
    largest = area[ranked[0]]
    return labels, [groups[key] for key in ranked if area[key] >= ARM_CANDIDATE_FRACTION * largest]


def _projected_tube(result: ShapeResult, camera: Camera, image_size: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: ``result``'s tube as ``camera`` sees it, widened by ``FOLLOW_MARGIN_PX``: a disc per
    centreline point (points less than 1 mm in front of the camera left out)."""
    centre = np.asarray(result.centerline_cam_m, dtype=np.float64)
    radii = np.interp(np.linspace(0.0, 1.0, len(centre)), np.linspace(0.0, 1.0, len(result.radii_m)), result.radii_m)
    front = centre[:, 2] > 1e-3
    out = np.zeros(image_size, np.uint8)
    if not front.any():
        return out.astype(bool)
    uv, _ = cv2.projectPoints(centre[front], np.zeros(3), np.zeros(3), camera.K_array(), camera.dist_array())
    uv = np.clip(uv.reshape(-1, 2), -1e5, 1e5)
    radius_px = np.clip(camera.fx * radii[front] / centre[front, 2] + FOLLOW_MARGIN_PX, 1.0, 1e5)
    for (u, v), r in zip(uv, radius_px):
        cv2.circle(out, (int(round(u)), int(round(v))), int(math.ceil(r)), 1, thickness=-1)
    return out.astype(bool)


def _prefit_loss(mask: np.ndarray, robot: ContinuumRobot, camera: Camera, config: ShapeFitConfig,
                 base_pixel: tuple[float, float] | None) -> float:
    """The lowest pre-fit loss (``_FitProblem.skeleton_loss``, order 2) of the fit's hypotheses on one component:
    what ``reconstruct_shape`` would start its rendered fit from."""
    bezier = dataclasses.replace(config, model="bezier", order=2)
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                               rim_offset_px=config.known_rim_offset_px)
    hypotheses = max(config.starts, config.prefit_starts)
    initial = initial_control_points(observation, robot, hypotheses, torch.Generator().manual_seed(config.seed),
                                     order=2)
    states = control_points_to_state(initial).to(torch.float32)
    problem = _FitProblem(observation, robot, bezier, torch.float32)
    if config.prefit_iterations:
        lr = config.lr_control * robot.length_m / float(initial[..., 2].mean())
        states = _prefit(problem, states, problem.skeleton_loss, bezier, lr)
    with torch.no_grad():
        loss = problem.skeleton_loss({"control": states, "radius_offsets": torch.zeros(len(states), robot.n_rings)}, 0)
    return float(loss.min())


RIM_SEARCH_PX = (-2.0, -1.0, 1.0, 2.0)  # rim offsets (full-image px) tried by rim_offset_px="auto", beside 0
RIM_SEARCH_MARGIN = 0.0005  # ... one kept when its loss is this much below the refit's at 0 (F frames: / sqrt F)
RIM_SEARCH_ITERATIONS = 100  # rendered steps of each offset's refit


@dataclass(frozen=True, kw_only=True)
class RimSearch:
    """Outcome of :func:`search_rim_offset`.

    Fields:
        offset_px: the rim offset kept, full-image pixels (0: the masks taken as exact).
        losses: offset -> the frames' mean loss refitted at it (0 included), the offsets of ``RIM_SEARCH_PX``.
        results: per frame, its refit at the kept offset (``rim_offset_px`` set), in the order given; the fits
            given, as they are, when 0 was kept.
        seconds: wall time of the search.
    """

    offset_px: float
    losses: dict[float, float]
    results: list[ShapeResult]
    seconds: float


def search_rim_offset(
    masks: Sequence[np.ndarray],
    results: Sequence[ShapeResult],
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    *,
    fixed_base_cam_m: np.ndarray | None = None,
) -> RimSearch:
    """The rim offset (``ShapeFitConfig.rim_offset_px``) that best explains masks of one segmenter, e.g. one
    image or a video's first frames, given their fits taken as exact.

    Every frame is refitted at 0 and at each offset of ``RIM_SEARCH_PX``, all in one batch
    (``reconstruct_shapes_warm``'s batch; one per Bezier order): a warm fit from its answer, first scaled about the
    camera centre by the depth the offset implies (the arm's mean apparent radius over itself less the offset), with
    the Levenberg-Marquardt pre-fit, the scaled answer kept as it is beside it, the straight-line depth hypothesis
    and ``RIM_SEARCH_ITERATIONS`` rendered steps. The offset of the lowest mean loss over the frames is kept when it
    is ``RIM_SEARCH_MARGIN / sqrt(F)`` below the mean at 0 (refitted alike, so that no offset wins by its extra
    steps; the margin shrinks as the mean of F frames' noise does). A segmenter's bias is the same on every frame
    while the loss's noise is not: over a video's first 8 frames the right offset came out on 18 of 18 tuning
    cases, from its first frame alone on 15 (``docs/tracking.md``).

    Args:
        masks: F ``(H, W)`` bool masks, as taken by ``camera``.
        results: their fits with the rim offset 0 (``reconstruct_shape`` or a tracker's), Bezier curves.
        robot, camera, config: as the fits took them (``config``'s iterations and starts are not used).
        fixed_base_cam_m: ``(2, 3)`` base point and direction held, as ``reconstruct_shape``.

    Returns:
        RimSearch.

    Raises:
        ConfigError: masks and results of different lengths or none, a result of another model or rim offset.
        ShapeError: a mask the refits cannot use (as the fit itself would raise).
    """
    t0 = time.perf_counter()
    if len(masks) != len(results) or not masks:
        raise ConfigError(f"masks, results: expected as many of each (>= 1), got {len(masks)} and {len(results)}")
    for result in results:
        if result.model != "bezier" or result.rim_offset_px != 0.0:
            raise ConfigError(f"results: expected Bezier fits with the rim offset 0, got model {result.model!r}, "
                              f"rim offset {result.rim_offset_px!r}")
    base = None if fixed_base_cam_m is None else _checked_base(fixed_base_cam_m)
    offsets = (0.0, *RIM_SEARCH_PX)
    warm = dataclasses.replace(config, iterations=RIM_SEARCH_ITERATIONS, starts=1, prefit_iterations=10,
                               prefit_solver="lm", warm_hypotheses=(1,), warm_keep_start=True, rim_offset_px=0.0,
                               multi_start_fraction=1.0, progress=False)
    refits: dict[tuple[int, float], ShapeResult] = {}
    for order in sorted({result.order for result in results}):  # a batch's starts share one order
        frames = [i for i, result in enumerate(results) if result.order == order]
        jobs = [(i, offset) for i in frames for offset in offsets]
        pixels = {i: tuple(float(v) for v in results[i].skeleton_px[0]) for i in frames}
        radius = {i: _mean_apparent_radius(masks[i], camera, config, robot, pixels[i]) for i in frames}
        starts = [results[i].control_points_cam_m * (radius[i] / max(radius[i] - offset, 0.2 * radius[i]))
                  for i, offset in jobs]
        with single_torch_thread():
            outcomes = _reconstruct_warm_batch([masks[i] for i, _ in jobs], robot, camera, warm, starts,
                                               [pixels[i] for i, _ in jobs], base, time.perf_counter(),
                                               rim_offsets_px=[offset for _, offset in jobs])
        for job, outcome in zip(jobs, outcomes):
            if isinstance(outcome, ShapeError):  # as the fit itself would have raised
                raise outcome
            refits[job] = outcome
    losses = {offset: float(np.mean([refits[i, offset].loss for i in range(len(results))])) for offset in offsets}
    best = min(RIM_SEARCH_PX, key=lambda offset: losses[offset])
    kept = best if losses[best] < losses[0.0] - RIM_SEARCH_MARGIN / math.sqrt(len(results)) else 0.0
    chosen = list(results) if kept == 0.0 else [refits[i, kept] for i in range(len(results))]
    return RimSearch(offset_px=kept, losses=losses, results=chosen, seconds=time.perf_counter() - t0)


def _mean_apparent_radius(mask: np.ndarray, camera: Camera, config: ShapeFitConfig, robot: ContinuumRobot,
                          base_pixel: tuple[float, float]) -> float:
    """The arm's mean apparent radius in ``mask``, full-image pixels: the skeleton's radii over its middle 80 %,
    weighted by ``r^2`` (as the pre-fit's width term)."""
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m)
    n = len(observation.radius_px)
    radius = observation.radius_px[n // 10: n - n // 10] / math.sqrt(observation.scale[0] * observation.scale[1])
    return float((radius**3).sum() / max((radius**2).sum(), 1e-12))


def _rim_search(mask: np.ndarray, robot: ContinuumRobot, camera: Camera, config: ShapeFitConfig,
                result: ShapeResult, fixed_base: np.ndarray | None) -> ShapeResult:
    """``rim_offset_px="auto"`` after the fit ``result`` (rim offset 0): :func:`search_rim_offset` of its one
    mask; an offset kept replaces the answer's curve, radii and loss by its refit's, the other fields (history,
    order losses, starts) stay the fit's own."""
    search = search_rim_offset([mask], [result], robot, camera, config, fixed_base_cam_m=fixed_base)
    fields = {} if search.offset_px == 0.0 else {name: getattr(search.results[0], name) for name in (
        "control_points_cam_m", "radii_m", "centerline_cam_m", "loss")}
    return dataclasses.replace(result, **fields, rim_offset_px=search.offset_px, rim_offset_losses=search.losses,
                               seconds=result.seconds + search.seconds)


def _checked_start(start: np.ndarray) -> np.ndarray:
    """A warm start as ``(n+1, 3)`` float64 control points, or ``ShapeError`` naming what is wrong."""
    initial = np.asarray(start, dtype=np.float64)
    if (initial.ndim != 2 or initial.shape[1] != 3 or len(initial) < 2 or not np.isfinite(initial).all()
            or not (initial[:, 2] > 0).all()):
        raise ShapeError(
            "initial_control_points_cam_m: expected (n + 1, 3) finite control points (n >= 1, the Bezier order "
            f"the warm fit keeps) at depth z > 0, got shape {initial.shape}"
        )
    return initial


def _checked_base(fixed_base: np.ndarray) -> np.ndarray:
    """A held base as ``(2, 3)`` float64 (point, unit direction), or ``ShapeError`` naming what is wrong."""
    base = np.asarray(fixed_base, dtype=np.float64)
    if (base.shape != (2, 3) or not np.isfinite(base).all() or not base[0, 2] > 0
            or abs(float(np.linalg.norm(base[1])) - 1.0) > 1e-6):
        raise ShapeError("fixed_base_cam_m: expected (2, 3) = (a base point at depth z > 0, a unit direction), "
                         f"got {base.tolist() if base.size <= 6 else base.shape}")
    return base


def _score(result: ShapeResult, config: ShapeFitConfig) -> float:
    """A result's loss plus the automatic order's penalty for its control points beyond the first order's, so that
    fits of different orders compare as the order search compares them (the loss alone for ``model="pcc"``)."""
    if result.model == "pcc":
        return result.loss
    return result.loss + config.order_penalty * (result.order - config.orders[0])


def sharpest_bend(control_points: torch.Tensor, radii: torch.Tensor, samples: int = 101) -> float:
    """The sharpest bend of a tube along a Bezier centreline: the largest curvature times the tube's radius there.

    Args:
        control_points: ``(n+1, 3)`` the centreline's control points (metres).
        radii: ``(R,)`` the tube's radii (metres) at ``R`` rings evenly spread in arc length, base first.
        samples: curve parameters evaluated, evenly spread in [0, 1].

    Returns:
        ``max kappa(s) * r(s)``: 0 for a straight tube, 1 where the bend's radius is the tube's own (its inner
        side folded to nothing); finite (a vanishing tangent is guarded, never NaN).
    """
    control = control_points.detach().to("cpu", torch.float64)[None]  # a number, on any device
    radii = torch.as_tensor(radii).detach().to("cpu", torch.float64)[None]
    s = torch.linspace(0.0, 1.0, samples, dtype=torch.float64)
    first, second = bezier_derivative(control, s, 1)[0], bezier_derivative(control, s, 2)[0]  # (S, 3) each
    speed = first.norm(dim=-1)
    curvature = torch.linalg.cross(first, second, dim=-1).norm(dim=-1) / speed.clamp_min(1e-12) ** 3
    radius = radius_profile_at(radii, arc_length_fractions(bezier_points(control, s)))[0]  # (S,) the taper's
    return float((curvature * radius).max())


def _reconstruct(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    base_pixel: tuple[float, float] | None,
    start: np.ndarray | None,
    fixed_base: np.ndarray | None = None,
    moments: Mapping[str, AdamMoments] | None = None,
) -> ShapeResult:
    t0 = time.perf_counter()
    starts = config.starts if start is None else 1 + len(config.warm_hypotheses)
    keep_start = start is not None and config.warm_keep_start and config.prefit_iterations > 0
    together_steps = max(1, round(config.iterations * config.multi_start_fraction))  # of the first order's starts
    n_all = together_steps if starts > 1 else config.iterations
    orders = config.orders if start is None else (len(start) - 1,)  # a warm start keeps its order
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                               rim_offset_px=config.known_rim_offset_px)
    generator = torch.Generator().manual_seed(config.seed)
    dtype = torch.float32
    if start is None:
        hypotheses = max(starts, config.prefit_starts) if config.prefit_iterations else starts
        initial = initial_control_points(observation, robot, hypotheses, generator, order=orders[0])  # (hyp., n+1, 3)
    else:
        initial = _warm_starts(start, observation, robot, config, generator)
    control = control_points_to_state(initial).to(dtype)
    lr = config.lr_control * robot.length_m / float(initial[..., 2].mean())  # radians and relative depth per step
    problem = _FitProblem(observation, robot, config, dtype, fixed_base)
    skeleton_loss, rendered_loss = (_compiled_losses(problem) if config.compile
                                    else (problem.skeleton_loss, problem.loss_and_gradients))
    t_prefit = time.perf_counter()

    def prefit_and_select(groups: list[torch.Tensor], keeps: list[int]) -> list[torch.Tensor]:
        """The pre-fit (no rendering) of each group of states ``(H_i, n_i+1, 3)`` (groups of several orders in one
        batch: a step's time is mostly its number of small operations, not the batch size), then of each group
        the ``keep`` that one render finds best."""
        if not config.prefit_iterations:
            return [group[:keep] for group, keep in zip(groups, keeps)]
        if len(groups) == 1:
            padded, layout, loss = groups[0], None, skeleton_loss
        else:
            padded, layout = _pad_states(groups)
            loss = functools.partial(problem.skeleton_loss, layout=layout)
        fitted = _prefit(problem, padded, loss, config, lr, layout)
        kept = []
        for control, keep in zip([fitted] if layout is None else _split_states(fitted, layout), keeps):
            if len(control) > keep:  # the hypotheses that already match the mask best go on
                with torch.no_grad():
                    rendered = problem.loss({"control": control, "radius_offsets": torch.zeros(
                        len(control), robot.n_rings, dtype=dtype)}, 0)
                control = control[torch.argsort(rendered)[:keep]]
            kept.append(control.contiguous())
        return kept

    # Each further order's fresh hypotheses come from the mask alone, so they are pre-fitted with the first order's,
    # in one batch, before the search knows how many orders it will try (a pre-fit step's time is mostly its number
    # of operations: 36 states cost about as much as 18 and 6 apart, docs/soft-arms.md).
    further = orders[1:] if config.order_starts > 1 else ()
    fresh_states = [control_points_to_state(initial_control_points(
        observation, robot, config.order_hypotheses, generator, order=order)).to(dtype) for order in further]
    control, *kept = prefit_and_select([control, *fresh_states], [starts] + [config.order_starts - 1] * len(further))
    fresh = dict(zip(further, kept))  # order -> its fresh starts' states, pre-fitted
    if keep_start:  # the warm start as given goes on too, after the pre-fitted ones
        control, starts = torch.cat([control, control_points_to_state(initial[:1]).to(dtype)]), starts + 1
    rates = None
    if start is not None and config.warm_slow_start > 0:  # the pre-fitted warm start again, slower, last
        control, starts = torch.cat([control, control[:1]]), starts + 1
        rates = torch.ones(starts, dtype=dtype)
        rates[-1] = config.warm_slow_start
    offsets = torch.zeros(starts, robot.n_rings, dtype=dtype)
    t1 = time.perf_counter()

    def rate(iteration: int) -> float:  # the learning-rate factor of the whole run at an iteration
        return config.final_lr_factor ** (iteration / max(config.iterations - 1, 1))

    def run(control: torch.Tensor, offsets: torch.Tensor, first: int, count: int, last: int | None = None,
            rates: torch.Tensor | None = None, begin: Mapping[str, AdamMoments] | None = None) -> FitResult:
        last = first + count - 1 if last is None else last
        return fit(
            {
                "control": ParamGroup(init=control, lr=lr * rate(first), start_rates=rates),
                "radius_offsets": ParamGroup(init=offsets, lr=config.lr_radius * robot.base_radius_m * rate(first),
                                             start_rates=rates),
            },
            rendered_loss,
            iterations=count,
            progress=config.progress,
            description="shape",
            final_lr_factor=rate(last) / rate(first),
            fused_adam=True,
            moments=begin,
        )

    warmup = together_steps if config.order_warmup_iterations is None else config.order_warmup_iterations
    warmup = warmup if config.order_starts > 1 else 0  # the fresh starts' steps alone at each further order
    extra = (warmup + config.order_iterations) * (len(orders) - 1)
    history = torch.full((config.iterations + extra, starts), math.nan, dtype=torch.float64)
    racing = {"control": control, "radius_offsets": offsets} | ({} if rates is None else {"start_rates": rates})
    stage_fits: list[FitResult] = []  # the race's stages, the last one's winner is the first order's answer

    def race_stage(params: dict[str, torch.Tensor], first: int, count: int) -> FitResult:
        stage_fits.append(run(params["control"], params["radius_offsets"], first, count,
                              rates=params.get("start_rates"), begin=moments if first == 0 else None))
        return stage_fits[-1]

    best, loss, best_start, start_losses = _race(race_stage, racing, _race_stages(config, starts), history)
    def score(order: int) -> float:  # an order's loss plus the penalty of its extra control points
        return fits[order][0] + config.order_penalty * (order - orders[0])

    def bend(order: int) -> float:  # its curve's sharpest bend relative to the tube (``sharpest_bend``)
        params = fits[order][1]
        return sharpest_bend(problem.control_points(params["control"][None].detach().to(torch.float64))[0],
                             problem.radii(params["radius_offsets"][None].detach().to(torch.float64))[0])

    fits = {orders[0]: (loss, best)}
    order_moments = {orders[0]: stage_fits[-1].moments_of()}  # its best start is the race's winner
    chosen, row = orders[0], config.iterations
    first, last = n_all, config.iterations - 1  # each further order's rate runs as the fit's from n_all to its end
    together_count = max(1, round(config.order_iterations * config.multi_start_fraction))
    for order in orders[1:]:  # each order warm-started from the previous one's curve, one more control point
        previous = problem.control_points(best["control"][None].to(torch.float64))
        candidates = control_points_to_state(elevate_bezier_degree(previous)).to(dtype)  # (1, n+1, 3)
        offsets = best["radius_offsets"][None]  # (1, n_rings)
        if config.order_starts > 1:  # fresh hypotheses of this order, from the mask, compete with the elevated curve
            states, state_offsets = fresh[order], torch.zeros(len(fresh[order]), robot.n_rings, dtype=dtype)
            if warmup:  # the fresh starts first get the steps the first order's starts got before its race ended
                warm = run(states, state_offsets, 0, warmup, first)
                history[row:row + warmup, best_start] = warm.history.amin(dim=1)
                row += warmup
                states, state_offsets = warm.best_params["control"], warm.best_params["radius_offsets"]
            candidates = torch.cat([candidates, states])  # (C, n+1, 3), the elevated curve first
            offsets = torch.cat([offsets, state_offsets])
        if len(candidates) > 1 and together_count < config.order_iterations:
            split = first + round((last - first) * together_count / config.order_iterations)
            both = run(candidates, offsets, first, together_count, split)
            history[row:row + together_count, best_start] = both.history.amin(dim=1)
            kept = both.params_of()
            refined = run(kept["control"][None], kept["radius_offsets"][None], split,
                          config.order_iterations - together_count, last)
            history[row + together_count:row + config.order_iterations, best_start] = refined.history[:, 0]
            best, value = refined.params_of(), float(refined.best_loss[0])  # its first step is the kept start
            order_moments[order] = refined.moments_of()
        else:
            refined = run(candidates, offsets, first, config.order_iterations, last)
            history[row:row + config.order_iterations, best_start] = refined.history.amin(dim=1)
            best, value = refined.params_of(), float(refined.best_loss[refined.best_start])
            order_moments[order] = refined.moments_of()
        row += config.order_iterations
        fits[order] = (value, best)
        if score(order) >= score(chosen):
            break  # one more control point did not pay for itself: the higher orders are not tried
        if config.max_bend and (bends := bend(order)) > config.max_bend >= bend(chosen):
            log.info("shape: order %d bends to curvature x tube radius %.2f (max_bend %g): not chosen",
                     order, bends, config.max_bend)
            break  # a loop no tube bends into: covering something the arm is not (e.g. a blob touching it)
        chosen = order
    history = history[:row]
    order_losses = {order: value for order, (value, _) in fits.items()}
    loss, best = fits[chosen]
    t2 = time.perf_counter()
    log.info("shape: working image %dx%d, order %d (losses %s), loss %.4g (start %d of %d), %.2f s preprocess, "
             "%.2f s pre-fit, %.2f s fit", observation.camera.width, observation.camera.height, chosen,
             ", ".join(f"{n}: {v:.4g}" for n, v in order_losses.items()), loss, best_start, starts,
             t_prefit - t0, t1 - t_prefit, t2 - t1)
    order_control = {order: problem.control_points(params["control"][None].detach().to(torch.float64))[0].numpy()
                     for order, (_, params) in fits.items()}
    control = torch.from_numpy(order_control[chosen])
    radii = problem.radii(best["radius_offsets"][None].to(torch.float64).detach())[0]
    return ShapeResult(
        control_points_cam_m=control.numpy(),
        radii_m=radii.numpy(),
        centerline_cam_m=bezier_centerline(control.numpy(), CENTERLINE_POINTS),
        order=chosen,
        order_losses=order_losses,
        order_control_points=order_control,
        **_observation_fields(observation, camera),
        loss=loss,
        start_losses=start_losses.numpy().copy(),
        best_start=best_start,
        history=history.numpy(),
        iterations=row,
        keypoint_mode=config.keypoint_mode,
        preprocess_seconds=t_prefit - t0,
        prefit_seconds=t1 - t_prefit,
        fit_seconds=t2 - t1,
        seconds=time.perf_counter() - t0,
        moments=order_moments[chosen],
    )


def _check_rim_read(config: ShapeFitConfig, where: str) -> None:
    """Refuse ``rim_offset_px="image"`` where no image is taken (``where``: the function's name)."""
    if config.rim_offset_px == "image":
        raise ConfigError(f"rim_offset_px: {where} takes no image; read the offset first "
                          f"(pipeline.segment.image_rim_offset_px) and give the number")


def reconstruct_shapes_warm(
    masks: Sequence[np.ndarray],
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    *,
    initial_control_points_cam_m: Sequence[np.ndarray],
    base_pixels: Sequence[tuple[float, float] | None] | None = None,
    fixed_base_cam_m: np.ndarray | None = None,
    initial_moments: Mapping[str, AdamMoments] | None = None,
) -> list[ShapeResult | ShapeError]:
    """Warm-started fits of several frames of one video together, in one batch.

    Each frame is fitted as ``reconstruct_shape(mask, ..., initial_control_points_cam_m=start)`` fits it (its
    start beside ``config.warm_hypotheses`` built from its own mask, the pre-fit, ``config.iterations`` rendered
    steps, the lower loss kept), but every frame's starts run in the same batch of every step: a step's time is
    mostly its number of small tensor operations, so F frames cost far less than F fits one after the other
    (``docs/tracking.md``). The frames share one working image: the crop of their masks' union (``observe_mask``'s
    margin around it), shrunk to ``config.working_max_side``. With a single frame the result equals
    ``reconstruct_shape``'s warm fit.

    Args:
        masks: F ``(H, W)`` bool masks, as taken by ``camera``.
        robot, camera, config: as ``reconstruct_shape`` (a Bezier model; ``starts``, ``prefit_starts`` and the
            order search are not used: each frame keeps its start's order).
        initial_control_points_cam_m: F starts ``(n+1, 3)``, e.g. the last estimate (one order for all).
        base_pixels: per frame, ``(u, v)`` of the base in the undistorted image (the skeleton end nearer it is the
            base), or ``None`` meaning *unknown*; ``None`` for all unknown.
        fixed_base_cam_m: ``(2, 3)`` base point and direction held in every frame, as ``reconstruct_shape``.
        initial_moments: Adam's state every frame's starts begin with (the estimate before the batch's
            ``ShapeResult.moments``), as ``reconstruct_shape``; ``None``: Adam's zeros.

    Returns:
        Per frame, its ``ShapeResult`` (``seconds`` and its parts: the batch's, shared equally), or the
        ``ShapeError`` its mask raised (empty, no skeleton path), in order.

    Raises:
        ShapeError: starts of different orders or not in front of the camera, a bad ``fixed_base_cam_m``.
        ConfigError: ``config.model`` is not ``"bezier"``, a mask of another size than the camera's, lengths
            that differ.
    """
    t0 = time.perf_counter()
    if config.model != "bezier":
        raise ConfigError(f"config.model: warm-started batches fit Bezier curves, got {config.model!r}")
    _check_rim_read(config, "reconstruct_shapes_warm")
    starts_in = [_checked_start(start) for start in initial_control_points_cam_m]
    pixels = [None] * len(masks) if base_pixels is None else list(base_pixels)
    if not (len(starts_in) == len(masks) == len(pixels)) or not masks:
        raise ConfigError(f"masks, initial_control_points_cam_m, base_pixels: expected as many of each (>= 1), got "
                          f"{len(masks)}, {len(starts_in)}, {len(pixels)}")
    if len({start.shape for start in starts_in}) != 1:
        raise ShapeError("initial_control_points_cam_m: expected starts of one Bezier order, got shapes "
                         f"{sorted({start.shape for start in starts_in})}")
    if len(masks) == 1:  # nothing to share: the single fit itself (bit for bit)
        try:
            return [reconstruct_shape(masks[0], robot, camera, config, base_pixel=pixels[0],
                                      initial_control_points_cam_m=starts_in[0], fixed_base_cam_m=fixed_base_cam_m,
                                      initial_moments=initial_moments)]
        except ShapeError as error:
            return [error]
    base = None if fixed_base_cam_m is None else _checked_base(fixed_base_cam_m)
    with single_torch_thread():
        return _reconstruct_warm_batch(masks, robot, camera, config, starts_in, pixels, base, t0,
                                       moments=initial_moments)


def _reconstruct_warm_batch(
    masks: Sequence[np.ndarray],
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    starts_in: list[np.ndarray],
    pixels: list[tuple[float, float] | None],
    fixed_base: np.ndarray | None,
    t0: float,
    rim_offsets_px: Sequence[float] | None = None,
    moments: Mapping[str, AdamMoments] | None = None,
) -> list[ShapeResult | ShapeError]:
    """:func:`reconstruct_shapes_warm` of two or more frames on checked starts: the observations in the masks'
    common crop, the starts of every frame in one batch (frame-major: its start, then its hypotheses), the pre-fit
    and the rendered fit over all of them, each frame's lowest loss kept. ``rim_offsets_px``: per frame, the rim
    offset it is fitted with (``None``: ``config``'s for all; the rim search fits one mask at several); ``moments``:
    Adam's state every start begins with (``None``: zeros)."""
    rims = [config.known_rim_offset_px] * len(masks) if rim_offsets_px is None else [float(r) for r in rim_offsets_px]
    outcomes: list[ShapeResult | ShapeError | None] = [None] * len(masks)
    fulls = {}
    for i, mask in enumerate(masks):
        try:
            fulls[i] = _undistorted_arm(mask, camera)
        except ShapeError as error:
            outcomes[i] = error
    box = _crop_box(*fulls.values()) if fulls else None
    observations = {}
    for i, full in fulls.items():
        try:
            observations[i] = _observe(full, camera, box, max_side=config.working_max_side,
                                       keypoints=config.keypoint_count, base_pixel=pixels[i],
                                       taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                                       rim_offset_px=rims[i])
        except ShapeError as error:
            outcomes[i] = error
    if not observations:
        return outcomes
    frames = sorted(observations)
    dtype = torch.float32
    order = len(starts_in[0]) - 1
    initial = []
    for i in frames:  # per frame its starts, as the single warm fit builds them
        initial.append(_warm_starts(starts_in[i], observations[i], robot, config,
                                    torch.Generator().manual_seed(config.seed)))
    prefitted = 1 + len(config.warm_hypotheses)  # starts per frame that the pre-fit moves
    keep_start = config.warm_keep_start and config.prefit_iterations > 0
    slow = config.warm_slow_start > 0
    per_frame = prefitted + keep_start + slow
    initial = torch.cat(initial)  # (F * prefitted, n+1, 3)
    control = control_points_to_state(initial).to(dtype)
    lr = config.lr_control * robot.length_m / float(initial[..., 2].mean())
    problems = [_FitProblem(observations[i], robot, config, dtype, fixed_base) for i in frames]
    prefit_problem = _stack_problems(problems, torch.arange(len(frames)).repeat_interleave(prefitted))
    problem = _stack_problems(problems, torch.arange(len(frames)).repeat_interleave(per_frame))
    rendered_loss = _compiled_losses(problem)[1] if config.compile else problem.loss_and_gradients
    t_prefit = time.perf_counter()
    if config.prefit_iterations:
        skeleton_loss = _compiled_losses(prefit_problem)[0] if config.compile else prefit_problem.skeleton_loss
        control = _prefit(prefit_problem, control, skeleton_loss, config, lr)
    extra = []  # each frame's further starts, after its pre-fitted ones: (F, n+1, 3) each
    if keep_start:  # the warm start as given
        extra.append(control_points_to_state(initial[::prefitted]).to(dtype))
    if slow:  # the pre-fitted warm start again, at a slower rate
        extra.append(control[::prefitted])
    if extra:
        control = torch.cat([control.reshape(len(frames), prefitted, *control.shape[1:]),
                             torch.stack(extra, dim=1)], dim=1)
        control = control.reshape(-1, *control.shape[2:])
    count = len(control)
    rates = None
    if slow:
        rates = torch.ones(len(frames), per_frame, dtype=dtype)
        rates[:, -1] = config.warm_slow_start
        rates = rates.reshape(-1)
    t1 = time.perf_counter()
    result = fit({"control": ParamGroup(init=control, lr=lr, start_rates=rates),
                  "radius_offsets": ParamGroup(init=torch.zeros(count, robot.n_rings, dtype=dtype),
                                               lr=config.lr_radius * robot.base_radius_m, start_rates=rates)},
                 rendered_loss, iterations=config.iterations, progress=config.progress, description="shape",
                 final_lr_factor=config.final_lr_factor, fused_adam=True, moments=moments)
    t2 = time.perf_counter()
    share = 1.0 / len(frames)
    for k, i in enumerate(frames):
        columns = slice(k * per_frame, (k + 1) * per_frame)
        losses = result.best_loss[columns]
        best_start = int(torch.argmin(losses))
        column = k * per_frame + best_start
        state = result.best_params["control"][column][None].to(torch.float64)
        chosen = problem.control_points(state)[0].detach().numpy()
        radii = problem.radii(result.best_params["radius_offsets"][column][None].to(torch.float64).detach())[0]
        loss = float(losses[best_start])
        outcomes[i] = ShapeResult(
            control_points_cam_m=chosen,
            radii_m=radii.numpy(),
            centerline_cam_m=bezier_centerline(chosen, CENTERLINE_POINTS),
            order=order,
            order_losses={order: loss},
            order_control_points={order: chosen},
            **_observation_fields(observations[i], camera),
            loss=loss,
            start_losses=losses.numpy().copy(),
            best_start=best_start,
            history=result.history[:, columns].numpy().copy(),
            iterations=config.iterations,
            keypoint_mode=config.keypoint_mode,
            rim_offset_px=rims[i],
            preprocess_seconds=(t_prefit - t0) * share,
            prefit_seconds=(t1 - t_prefit) * share,
            fit_seconds=(t2 - t1) * share,
            seconds=(time.perf_counter() - t0) * share,
            moments=result.moments_of(column),
        )
    return outcomes


def _prefit(problem: "_FitProblem", states: torch.Tensor, skeleton_loss: Callable, config: ShapeFitConfig,
            lr: float, layout: Layout | None = None) -> torch.Tensor:
    """The pre-fit of states ``(S, n+1, 3)`` (padded with a ``layout``) by ``config.prefit_solver``:
    Levenberg-Marquardt steps on ``problem``, or Adam steps (rate ``lr``) of ``skeleton_loss`` (the problem's,
    compiled or bound to the layout), radius offsets held at 0. Returns the pre-fitted states."""
    if config.prefit_solver == "lm":
        return prefit_levenberg_marquardt(problem, states, config.prefit_iterations, layout)
    offsets = torch.zeros(len(states), problem.robot.n_rings, dtype=states.dtype)
    return fit({"control": ParamGroup(init=states, lr=lr), "radius_offsets": ParamGroup(init=offsets, lr=0.0)},
               skeleton_loss, iterations=config.prefit_iterations, description="shape pre-fit",
               final_lr_factor=config.final_lr_factor, fused_adam=True).best_params["control"]


def _warm_starts(start: np.ndarray, observation: ShapeObservation, robot: ContinuumRobot, config: ShapeFitConfig,
                 generator: torch.Generator) -> torch.Tensor:
    """A warm fit's starts ``(1 + len(config.warm_hypotheses), n+1, 3)``: the warm start ``(n+1, 3)``, then the
    mask's hypotheses ``config.warm_hypotheses`` it competes with (``initial_control_points``, its order)."""
    initial = torch.from_numpy(start)[None]
    if not config.warm_hypotheses:
        return initial
    built = initial_control_points(observation, robot, max(config.warm_hypotheses) + 1, generator,
                                   order=len(start) - 1, only=config.warm_hypotheses)
    return torch.cat([initial, built])


def _stack_problems(problems: Sequence["_FitProblem"], frame_of_start: torch.Tensor) -> "_FitProblem":
    """One problem whose starts see different frames' masks: ``problems`` share the working camera and image
    (one crop), and start ``s`` is scored against ``problems[frame_of_start[s]]``'s mask, skeleton and widths.
    The per-frame tensors get a leading start dimension (the losses broadcast over it)."""
    stacked = copy.copy(problems[0])
    for name in ("mask", "targets", "dense_targets", "dense_radius", "dense_width_weight"):
        setattr(stacked, name, torch.stack([getattr(p, name) for p in problems])[frame_of_start])
    dtype = stacked.mask.dtype
    for name in ("mask_area", "path_length"):
        setattr(stacked, name, torch.tensor([getattr(p, name) for p in problems], dtype=dtype)[frame_of_start])
    rims = torch.tensor([p.rim_offset_px for p in problems], dtype=dtype)[frame_of_start]
    stacked.rim_offset_px = rims[:, None]  # (S, 1): a frame's rim offset for each ring of its starts
    stacked.per_start = True
    return stacked


_PER_START_FIELDS = ("mask", "targets", "dense_targets", "dense_radius", "dense_width_weight", "mask_area",
                     "path_length", "rim_offset_px")  # the fields _stack_problems gives a leading start dimension


def _each_start_repeated(problem: "_FitProblem", repeats: int) -> "_FitProblem":
    """The problem of a batch in which every start of ``problem`` comes ``repeats`` times in a row (a stacked
    problem's per-start fields repeated to match; an unstacked one's broadcast as they are)."""
    if not problem.per_start:
        return problem
    repeated = copy.copy(problem)
    for name in _PER_START_FIELDS:
        if getattr(problem, name) is not None:
            setattr(repeated, name, getattr(problem, name).repeat_interleave(repeats, dim=0))
    return repeated


LM_DIFFERENCE_STEP = 1e-6  # forward-difference step of the pre-fit's Jacobian, state units (rays, log depth)
LM_MIN_DISTANCE_PX = 0.05  # the distance term's reweighting holds distances below this at it
LM_TOLERANCE = 1e-4  # a start is done once a step lowers its loss by less than this fraction
LM_FAILURES = 3  # ... or after this many steps in a row without a lower loss (its damping raised each time)


def prefit_levenberg_marquardt(problem: "_FitProblem", state: torch.Tensor, iterations: int,
                               layout: Layout | None = None) -> torch.Tensor:
    """The pre-fit (``_FitProblem.skeleton_loss``, radius offsets 0) by Levenberg-Marquardt steps, every start at
    once: ``(S, n+1, 3)`` states -> the pre-fitted states (same shape and dtype).

    The loss is ``c sum_k |d_k| + w_l e_l^2 + w_w sum_k w_k e_k^2``: the skeleton points' distances ``d_k``, the
    length and width errors (``skeleton_terms``). Each step replaces the distances by their quadratic majoriser at
    the current state (``|d| <= |d|^2 / (2 |d_0|) + |d_0| / 2``, iteratively reweighted least squares), takes the
    Jacobian of the residuals by forward differences (one batch of ``S (3(n+1) + 1)`` states, in float64), and
    tries three dampings of the Gauss-Newton step (Marquardt's scaling) in one batch; a start moves only to a state
    of lower loss. So each start's loss never rises, and a step costs about two evaluations of the loss (no
    backward pass), against Adam's one forward and backward per step of several times as many steps.

    Args:
        problem: the fit's problem (stacked or not); its dtype need not be float64.
        state: ``(S, n+1, 3)`` states (``control_points_to_state``; padded with a ``layout``, ``_pad_states``).
        iterations: at most this many steps; they end early once every start is done: its last step lowered its
            loss by less than ``LM_TOLERANCE`` of itself, or ``LM_FAILURES`` steps in a row found no lower loss
            (each raising its damping a hundredfold, so a first step too long for the problem is shortened).
    """
    S, N, _ = state.shape
    P = 3 * N
    f64 = problem.astype(torch.float64, skeleton_only=True)
    x = state.detach().to(torch.float64).reshape(S, P)
    probes = torch.cat([torch.zeros(1, P, dtype=torch.float64),
                        LM_DIFFERENCE_STEP * torch.eye(P, dtype=torch.float64)])  # (P+1, P)
    factors = torch.tensor([0.1, 1.0, 10.0], dtype=torch.float64)
    damping = torch.full((S,), 1e-3, dtype=torch.float64)
    failures = torch.zeros(S, dtype=torch.long)  # steps in a row without a lower loss, per start
    n_rings = problem.robot.n_rings

    def evaluate(states: torch.Tensor, repeats: int):  # (S * repeats, P) -> the terms and the loss
        repeated = _each_start_repeated(f64, repeats)
        scaled = None if layout is None else tuple((order, count * repeats) for order, count in layout)
        terms = repeated.skeleton_terms({"control": states.reshape(-1, N, 3),
                                         "radius_offsets": torch.zeros(len(states), n_rings, dtype=torch.float64)},
                                        scaled)
        return terms, repeated.skeleton_loss_of_terms(*terms)

    config = problem.config
    targets = f64.dense_targets
    D = targets.shape[-2]
    scale = 1.0 / (D * f64.path_length)  # the distance term's weight: a number, or (S,) stacked
    scale = scale.reshape(S, 1) if torch.is_tensor(scale) and scale.dim() else scale
    width_weight = (config.w_width * f64.dense_width_weight).sqrt()  # (D,) or (S, D)
    eye = torch.eye(P, dtype=torch.float64)
    with torch.no_grad():
        (model, _, _), loss = evaluate(x, 1)
        for _ in range(iterations):
            distance = (model - targets).norm(dim=-1)  # (S, D)
            weight = (scale / (2.0 * distance.clamp_min(LM_MIN_DISTANCE_PX))).sqrt()  # (S, D) the majoriser's
            (model_p, relative_p, length_p), _ = evaluate((x[:, None] + probes).reshape(-1, P), P + 1)
            offset = model_p.reshape(S, P + 1, D, 2) - (targets[:, None] if targets.dim() == 3 else targets)
            residuals = torch.cat([
                (weight[:, None, :, None] * offset).reshape(S, P + 1, 2 * D),
                (width_weight if width_weight.dim() == 1 else width_weight[:, None]) * relative_p.reshape(S, P + 1, D),
                math.sqrt(config.w_length) * length_p.reshape(S, P + 1, 1),
            ], dim=-1)  # (S, P+1, M)
            r0 = residuals[:, 0]  # (S, M)
            J = (residuals[:, 1:] - r0[:, None]) / LM_DIFFERENCE_STEP  # (S, P, M): row j the derivative along x_j
            A = J @ J.transpose(1, 2)  # (S, P, P)
            g = (J @ r0[..., None])[..., 0]  # (S, P)
            lam = damping[:, None] * factors  # (S, 3)
            system = (A[:, None] + lam[..., None, None] * torch.diag_embed(torch.diagonal(A, dim1=1, dim2=2))[:, None]
                      + 1e-12 * eye)  # (S, 3, P, P)
            steps = -torch.linalg.solve(system, g[:, None].expand(S, 3, P))  # (S, 3, P)
            candidates = (x[:, None] + steps).reshape(-1, P)  # (S * 3, P)
            (model_c, _, _), loss_c = evaluate(candidates, 3)
            loss_c = torch.where(torch.isfinite(loss_c), loss_c, torch.full_like(loss_c, math.inf)).reshape(S, 3)
            best_loss, best = loss_c.min(dim=1)  # (S,)
            better = best_loss < loss
            failures = torch.where(better, torch.zeros_like(failures), failures + 1)
            # A start is done once a step lowers its loss by less than LM_TOLERANCE of it, or after LM_FAILURES
            # steps in a row that found no lower loss (each raising its damping a hundredfold).
            moving = (better & (best_loss < loss * (1.0 - LM_TOLERANCE))) | (~better & (failures < LM_FAILURES))
            rows = torch.arange(S)
            x = torch.where(better[:, None], candidates.reshape(S, 3, P)[rows, best], x)
            model = torch.where(better[:, None, None], model_c.reshape(S, 3, D, 2)[rows, best], model)
            loss = torch.where(better, best_loss, loss)
            damping = torch.where(better, lam[rows, best], damping * 100.0).clamp(1e-9, 1e9)
            if not bool(moving.any()):
                break
    return x.reshape(S, N, 3).to(state.dtype)


def _race_stages(config: ShapeFitConfig, starts: int) -> list[tuple[int, int]]:
    """The stages of a multi-start fit: ``(starts kept, the iteration they run to)``, in turn: all ``starts`` to
    ``multi_start_fraction`` of ``config.iterations``, the best ``finalists`` of them to ``finalist_fraction``,
    then the best alone to the end (stages that would be empty are left out)."""
    n = config.iterations
    if starts == 1:
        return [(1, n)]
    stages = [(starts, min(n, max(1, round(n * config.multi_start_fraction))))]
    finalists, until = min(config.finalists, starts), min(n, round(n * config.finalist_fraction))
    if 1 < finalists < starts and until > stages[-1][1]:
        stages.append((finalists, until))
    if stages[-1][1] < n:
        stages.append((1, n))
    return stages


def _race(
    run: Callable[[dict[str, torch.Tensor], int, int], FitResult],
    params: dict[str, torch.Tensor],
    stages: list[tuple[int, int]],
    history: torch.Tensor,
) -> tuple[dict[str, torch.Tensor], float, int, torch.Tensor]:
    """Race the starts of ``params`` (name -> ``(S, ...)``) through ``stages`` (``_race_stages``).

    ``run(params, first, count)`` fits ``params`` from iteration ``first`` for ``count`` steps. Before each stage
    the starts of lowest loss so far go on. Fills ``history[:last stage's end]``'s columns of the starts that ran.
    Entries of ``params`` that the fit does not return (a per-start rate) go on with their starts.

    Returns:
        the winner's parameters (without the start dimension), its loss, its index in ``params``, and every
        start's lowest loss in the first stage ``(S,)``.
    """
    columns = torch.arange(next(iter(params.values())).shape[0])
    first, lowest, start_losses = 0, None, None
    for kept, until in stages:
        if lowest is not None and kept < len(columns):
            chosen = torch.argsort(lowest)[:kept]
            params, columns = {name: value[chosen] for name, value in params.items()}, columns[chosen]
        result = run(params, first, until - first)
        history[first:until, columns] = result.history
        params, lowest = {**params, **result.best_params}, result.best_loss  # a per-start rate goes on as it is
        start_losses = result.best_loss.clone() if start_losses is None else start_losses
        first = until
    winner = int(torch.argmin(lowest))
    return ({name: value[winner] for name, value in result.best_params.items()}, float(lowest[winner]),
            int(columns[winner]), start_losses)


def _observation_fields(observation: ShapeObservation, camera: Camera) -> dict:
    """The ``ShapeResult`` fields that come from the mask's observation (keypoints, skeleton, working size) and the
    camera (undistorted: the same ``K``, no distortion), shared by the Bezier and the PCC fits."""
    return {
        "keypoints_px": observation.to_full_resolution(observation.keypoints_px),
        "keypoint_fractions": observation.keypoint_fractions.copy(),
        "skeleton_px": observation.to_full_resolution(observation.path_px),
        "camera": Camera(K=camera.K, width=camera.width, height=camera.height),
        "working_size": observation.camera.image_size,
        "base_end_disputed": observation.base_end_disputed,
    }


def _reconstruct_pcc(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    base_pixel: tuple[float, float] | None,
) -> ShapeResult:
    """``reconstruct_shape`` with ``config.model == "pcc"``: by ``config.pcc_start``, the Bezier fit's answer
    refined as PCC sections (:func:`_pcc_from_bezier`), or the Bezier fit's hypotheses (order
    ``PCC_HYPOTHESIS_ORDER``) turned into PCC sections (``_pcc_initial_state``), then the same pre-fit, start
    selection, rendered fit and schedule as the Bezier fit (``_reconstruct``), with no order search."""
    if config.pcc_start == "bezier":
        return _pcc_from_bezier(mask, robot, camera, config, base_pixel)[1]
    t0 = time.perf_counter()
    starts = config.starts
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                               rim_offset_px=config.known_rim_offset_px)
    generator = torch.Generator().manual_seed(config.seed)
    dtype = torch.float32
    hypotheses = max(starts, config.prefit_starts) if config.prefit_iterations else starts
    control = initial_control_points(observation, robot, hypotheses, generator, order=PCC_HYPOTHESIS_ORDER)
    curves = torch.from_numpy(np.stack([bezier_centerline(c, 101) for c in control.numpy()]))  # (hyp., 101, 3)
    lengths = PccLengths(total_m=robot.length_m, fixed_m=config.section_lengths_m)
    state = {name: value.to(dtype) for name, value in _pcc_initial_state(curves, config.sections, lengths).items()}
    lr = config.lr_control * robot.length_m / float(control[..., 2].mean())
    rates = {"base": lr, "rotation": lr, "bend": lr, "length_logits": 0.0 if config.section_lengths_m else lr}
    problem = _FitProblem(observation, robot, config, dtype)
    t_prefit = time.perf_counter()

    def zeros(count: int) -> torch.Tensor:
        return torch.zeros(count, robot.n_rings, dtype=dtype)

    if config.prefit_iterations:
        prefit = fit({**{name: ParamGroup(init=value, lr=rates[name]) for name, value in state.items()},
                      "radius_offsets": ParamGroup(init=zeros(hypotheses), lr=0.0)},
                     problem.skeleton_loss, iterations=config.prefit_iterations, description="shape pre-fit (pcc)",
                     final_lr_factor=config.final_lr_factor)
        state = {name: prefit.best_params[name] for name in state}
        if hypotheses > starts:
            with torch.no_grad():
                rendered = problem.loss({**state, "radius_offsets": zeros(hypotheses)}, 0)
            keep = torch.argsort(rendered)[:starts]
            state = {name: value[keep] for name, value in state.items()}
    t1 = time.perf_counter()

    def rate(iteration: int) -> float:
        return config.final_lr_factor ** (iteration / max(config.iterations - 1, 1))

    def run(state: dict[str, torch.Tensor], offsets: torch.Tensor, first: int, count: int):
        groups = {name: ParamGroup(init=value, lr=rates[name] * rate(first)) for name, value in state.items()}
        groups["radius_offsets"] = ParamGroup(init=offsets, lr=config.lr_radius * robot.base_radius_m * rate(first))
        return fit(groups, problem.loss, iterations=count, progress=config.progress, description="shape (pcc)",
                   final_lr_factor=rate(first + count - 1) / rate(first), fused_adam=True)

    history = torch.full((config.iterations, starts), math.nan, dtype=torch.float64)
    best, loss, best_start, start_losses = _race(
        lambda params, first, count: run({name: params[name] for name in state}, params["radius_offsets"], first,
                                         count),
        {**state, "radius_offsets": zeros(starts)}, _race_stages(config, starts), history)
    t2 = time.perf_counter()
    log.info("shape (pcc, %d sections): start %d of %d", config.sections, best_start, starts)
    return _pcc_result(problem, best, lengths, loss, observation, camera, config, start_losses=start_losses.numpy(),
                       best_start=best_start, history=history.numpy(), iterations=config.iterations,
                       seconds=(t_prefit - t0, t1 - t_prefit, t2 - t1, time.perf_counter() - t0))


def _reconstruct_lower(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    base_pixel: tuple[float, float] | None,
) -> ShapeResult:
    """``reconstruct_shape`` with ``config.model == "auto"``: the Bezier fit and the PCC sections refined from it
    (``_pcc_from_bezier``), the one of lower loss kept (the Bezier fit on a tie), both losses in ``model_losses``,
    both fits' time in ``seconds``."""
    bezier, pcc = _pcc_from_bezier(mask, robot, camera, _sections_config(config), base_pixel,
                                   bezier_config=dataclasses.replace(config, model="bezier"))
    return _lower_loss(bezier, pcc, seconds=pcc.seconds)


def _sections_config(config: ShapeFitConfig, **changes) -> ShapeFitConfig:
    """``config`` (``model="auto"``) for the refinement of its Bezier fit into sections: ``model="pcc"``, and the
    pre-fit solver Adam (the refinement runs no pre-fit; ``"lm"`` is for Bezier curves only)."""
    return dataclasses.replace(config, model="pcc", prefit_solver="adam", **changes)


def _lower_loss(bezier: ShapeResult, pcc: ShapeResult, *, seconds: float) -> ShapeResult:
    """Of a Bezier fit and the PCC sections refined from it, the one of lower loss (the Bezier fit on a tie), with
    both losses in ``model_losses`` and ``seconds`` as given (both fits' time)."""
    kept = pcc if pcc.loss < bezier.loss else bezier
    log.info("shape (auto): loss %.4g Bezier (order %d), %.4g PCC (%d sections): %s kept", bezier.loss,
             bezier.order, pcc.loss, pcc.order, kept.model)
    return dataclasses.replace(kept, model_losses={"bezier": bezier.loss, "pcc": pcc.loss}, seconds=seconds)


def _pcc_from_bezier(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    base_pixel: tuple[float, float] | None,
    *,
    bezier_config: ShapeFitConfig | None = None,
) -> tuple[ShapeResult, ShapeResult]:
    """The PCC fit of ``config.pcc_start == "bezier"``: the Bezier fit of ``config`` (``_reconstruct``, its order
    search included), its centreline and its other orders' curves turned into ``config.sections`` arcs, each a
    start (``_refined_sections``), refined for ``config.pcc_iterations`` rendered steps, radius offsets held at 0.
    ``bezier_config``: the Bezier fit's settings, or ``None`` meaning ``config`` with ``model="bezier"``.
    Returns (the Bezier fit, the PCC fit). The PCC result's ``history`` is the Bezier fit's lowest loss at each of
    its steps, then the best start's; its pre-fit time includes the Bezier fit's, its ``seconds`` both fits'."""
    t0 = time.perf_counter()
    bezier_config = dataclasses.replace(config, model="bezier") if bezier_config is None else bezier_config
    bezier = _reconstruct(mask, robot, camera, bezier_config, base_pixel, None)
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                               rim_offset_px=config.known_rim_offset_px)
    t1 = time.perf_counter()
    problem, refined, lengths = _refined_sections(observation, robot, config, bezier, None, config.pcc_iterations,
                                                  fixed_base=None)
    t2 = time.perf_counter()
    with warnings.catch_warnings():  # columns of a start that stopped early are NaN from there on
        warnings.simplefilter("ignore", RuntimeWarning)
        bezier_history = np.nanmin(bezier.history, axis=1)
    history = np.concatenate([bezier_history, refined.history[:, refined.best_start].numpy()])[:, None]
    log.info("shape (pcc, %d sections): from the Bezier fit (order %d, loss %.4g)", config.sections, bezier.order,
             bezier.loss)
    best = refined.best_start
    return bezier, _pcc_result(problem, refined.params_of(), lengths, float(refined.best_loss[best]), observation,
                               camera, config, start_losses=refined.best_loss.numpy(), best_start=best,
                               history=history, iterations=bezier.iterations + config.pcc_iterations,
                               seconds=(bezier.preprocess_seconds, t1 - t0 - bezier.preprocess_seconds, t2 - t1,
                                        time.perf_counter() - t0))


def refine_pcc(
    mask: np.ndarray,
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig,
    bezier: ShapeResult,
    *,
    previous: PccParameters | None = None,
    iterations: int | None = None,
    base_pixel: tuple[float, float] | None = None,
    fixed_base_cam_m: np.ndarray | None = None,
) -> ShapeResult:
    """PCC sections fitted to ``mask`` from a Bezier fit of the same mask (e.g. each frame of a video,
    ``pipeline.track``): ``bezier``'s centreline turned into ``config.sections`` arcs (as ``model="pcc"`` does
    after its Bezier fit; the curves of its order search's other orders too, each a start) and, with ``previous``,
    those sections (e.g. the last frame's) as another start, all refined together by the rendered loss, the lowest
    loss kept.

    Args:
        mask: ``(H, W)`` bool, the arm's mask (one component: the one ``bezier`` fitted).
        robot, camera: as ``reconstruct_shape`` takes them.
        config: ``model="pcc"`` settings (sections, section lengths, working side, loss weights, rim offset).
        bezier: a Bezier ``ShapeResult`` of ``mask`` (``model="bezier"``).
        previous: sections to start from beside ``bezier``'s (``ShapeResult.pcc``), or ``None``.
        iterations: rendered steps (>= 1), at the rates of a fit's second half; ``None`` meaning
            ``config.pcc_iterations``.
        base_pixel: the base end of the mask's skeleton path, as ``reconstruct_shape`` takes it (for a warm frame,
            the Bezier answer's base).
        fixed_base_cam_m: ``(2, 3)`` base point and direction held (as ``reconstruct_shape`` takes them; the
            Bezier fit held them too): every start's base frame has that point and tangent (its roll ``previous``'s,
            or ``initial_normal``'s; the roll is free in the bends).

    Returns:
        A ``model="pcc"`` ``ShapeResult``: ``start_losses`` per start (``bezier``'s sections first, then its other
        orders' by order, then ``previous``), ``history`` ``(iterations, starts)``, ``iterations`` the
        refinement's steps.

    Raises:
        ConfigError: ``config.model`` is not ``"pcc"``, ``bezier`` is not a Bezier result, ``previous`` has
            another number of sections, ``iterations`` is not an int >= 1.
        ShapeError: a bad ``fixed_base_cam_m``.
    """
    if config.model != "pcc":
        raise ConfigError(f"config.model: refine_pcc fits sections, expected 'pcc', got {config.model!r}")
    _check_rim_read(config, "refine_pcc")
    if not isinstance(bezier, ShapeResult) or bezier.model != "bezier":
        raise ConfigError(f"bezier: expected a Bezier ShapeResult, got "
                          f"{bezier.model if isinstance(bezier, ShapeResult) else type(bezier).__name__!r}")
    if previous is not None and (not isinstance(previous, PccParameters)
                                 or len(previous.bends_rad) != config.sections):
        got = len(previous.bends_rad) if isinstance(previous, PccParameters) else type(previous).__name__
        raise ConfigError(f"previous: expected PccParameters of {config.sections} sections, got {got}")
    if iterations is not None:
        _int_at_least(iterations, 1, "iterations")
    count = config.pcc_iterations if iterations is None else iterations
    base = None if fixed_base_cam_m is None else _checked_base(fixed_base_cam_m)
    t0 = time.perf_counter()
    with single_torch_thread():  # as the fit (module docstring, Threads)
        observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                                   base_pixel=base_pixel, taper_ratio=robot.base_radius_m / robot.tip_radius_m,
                                   rim_offset_px=config.known_rim_offset_px)
        t1 = time.perf_counter()
        problem, refined, lengths = _refined_sections(observation, robot, config, bezier, previous, count,
                                                      fixed_base=base)
        t2 = time.perf_counter()
        best = refined.best_start
        return _pcc_result(problem, refined.params_of(), lengths, float(refined.best_loss[best]), observation,
                           camera, config, start_losses=refined.best_loss.numpy(), best_start=best,
                           history=refined.history.numpy(), iterations=count,
                           seconds=(t1 - t0, 0.0, t2 - t1, time.perf_counter() - t0))


def _refined_sections(observation: ShapeObservation, robot: ContinuumRobot, config: ShapeFitConfig,
                      bezier: ShapeResult, previous: PccParameters | None, iterations: int, *,
                      fixed_base: np.ndarray | None) -> tuple["_FitProblem", FitResult, PccLengths]:
    """The refinement of ``_pcc_from_bezier`` and ``refine_pcc``: ``bezier``'s centreline as sections
    (``_pcc_initial_state``: the arcs through its points, then a least-squares fit to them), the curves of its order
    search's other orders the same way (each a start: the chosen order's curve can bend in depth where no two arcs
    do, a lower order's often does not), and ``previous``'s sections (the last start), refined together for
    ``iterations`` rendered steps at the rates of a fit's second half, radius offsets held at 0; with
    ``fixed_base`` ``(2, 3)`` (point, direction) every start's base point and frame held there."""
    dtype = torch.float32
    lengths = PccLengths(total_m=robot.length_m, fixed_m=config.section_lengths_m)
    curve = torch.from_numpy(resample_polyline(bezier.centerline_cam_m, CENTERLINE_POINTS))[None]  # (1, P, 3)
    held = None
    if fixed_base is not None:  # the held point and tangent, with the previous frame's roll (the bends' reference)
        z = torch.from_numpy(fixed_base[1])[None]
        x = initial_normal(z, torch.zeros_like(z))
        R = (torch.from_numpy(previous.R_cam_base)[None] if previous is not None else
             torch.stack([x, torch.linalg.cross(z, x, dim=-1), z], -1))
        held = (torch.from_numpy(fixed_base[0])[None], R)
    state = _pcc_initial_state(curve, config.sections, lengths, base_frame=held)
    for order, control in sorted(bezier.order_control_points.items()):  # the order search's other curves
        if order != bezier.order:
            other = torch.from_numpy(resample_polyline(bezier_centerline(control, 201), CENTERLINE_POINTS))[None]
            other = _pcc_initial_state(other, config.sections, lengths, base_frame=held)
            state = {name: torch.cat([value, other[name]]) for name, value in state.items()}
    if previous is not None:  # as they are: fitted to this frame's curve they would take on its flaws
        before = _pcc_state_of(previous, curve.dtype)
        if held is not None:
            before.update(base=state["base"], rotation=state["rotation"])
        state = {name: torch.cat([value, before[name]]) for name, value in state.items()}
    state = {name: value.to(dtype) for name, value in state.items()}
    starts = len(state["base"])
    lr = config.lr_control * robot.length_m / float(bezier.control_points_cam_m[:, 2].mean())
    rates = {"base": 0.0 if held else lr, "rotation": 0.0 if held else lr, "bend": lr,
             "length_logits": 0.0 if config.section_lengths_m else lr}
    problem = _FitProblem(observation, robot, config, dtype)
    start = config.final_lr_factor ** 0.5  # the rate of a fit's second half: the start is already converged
    groups = {name: ParamGroup(init=value, lr=rates[name] * start) for name, value in state.items()}
    groups["radius_offsets"] = ParamGroup(init=torch.zeros(starts, robot.n_rings, dtype=dtype), lr=0.0)
    refined = fit(groups, problem.loss, iterations=iterations, progress=config.progress, description="shape (pcc)",
                  final_lr_factor=config.final_lr_factor / start, fused_adam=True)
    return problem, refined, lengths


def _pcc_state_of(pcc: PccParameters, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """The PCC fit's state ``(1, ...)`` of fitted sections (the inverse of ``pcc_state_to_parameters``; the
    length logits are the lengths' logarithms, whose softmax gives the same shares)."""
    def tensor(value: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(value, dtype=np.float64))[None].to(dtype)

    return {"base": control_points_to_state(tensor(pcc.base_cam_m)[:, None])[:, 0],
            "rotation": rotation_to_6d(tensor(pcc.R_cam_base)), "bend": tensor(pcc.bends_rad),
            "length_logits": torch.log(tensor(pcc.section_lengths_m).clamp_min(1e-12))}


def _pcc_result(problem: "_FitProblem", best: dict[str, torch.Tensor], lengths: PccLengths, loss: float,
                observation: ShapeObservation, camera: Camera, config: ShapeFitConfig, *, start_losses: np.ndarray,
                best_start: int, history: np.ndarray, iterations: int,
                seconds: tuple[float, float, float, float]) -> ShapeResult:
    """The ``ShapeResult`` of a PCC fit's best state ``best`` (one start's parameters, unbatched) and its loss;
    ``seconds``: (preprocess, pre-fit, fit, total)."""
    with torch.no_grad():
        base, R, bends, section_lengths = pcc_state_to_parameters(
            {name: best[name][None].to(torch.float64) for name in ("base", "rotation", "bend", "length_logits")},
            lengths)
    pcc = PccParameters(base_cam_m=base[0].numpy(), R_cam_base=R[0].numpy(), bends_rad=bends[0].numpy(),
                        section_lengths_m=section_lengths[0].numpy())
    log.info("shape (pcc, %d sections): working image %dx%d, loss %.4g, curvatures %s 1/m, %.2f s preprocess, "
             "%.2f s pre-fit, %.2f s fit", config.sections, observation.camera.width, observation.camera.height, loss,
             np.round(pcc.curvatures_per_m, 2), *seconds[:3])
    radii = problem.radii(best["radius_offsets"][None].to(torch.float64).detach())[0]
    ends = pcc.points(1)  # (N+1, 3) base, joints, tip
    return ShapeResult(
        control_points_cam_m=ends,
        radii_m=radii.numpy(),
        centerline_cam_m=resample_polyline(pcc.points(PCC_DENSE_SAMPLES), CENTERLINE_POINTS),
        order=config.sections,
        order_losses={config.sections: loss},
        order_control_points={config.sections: ends},
        **_observation_fields(observation, camera),
        loss=loss,
        start_losses=np.asarray(start_losses).copy(),
        best_start=best_start,
        history=history,
        iterations=iterations,
        keypoint_mode=config.keypoint_mode,
        preprocess_seconds=seconds[0],
        prefit_seconds=seconds[1],
        fit_seconds=seconds[2],
        seconds=seconds[3],
        model="pcc",
        pcc=pcc,
    )


def reconstruct_shape_from_image(
    image: np.ndarray,
    segmenter: Callable[[np.ndarray], np.ndarray],
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeFitConfig = ShapeFitConfig(),
    *,
    base_pixel: tuple[float, float] | None = None,
) -> ShapeResult:
    """``reconstruct_shape(segmenter(image), ...)``: segment a colour image (``(H, W, 3)`` uint8 BGR) first.

    A segmenter that keeps every component (``largest_component=False``, as ``shape --image`` segments) lets the
    fit choose the arm's among clutter and join the pieces of an arm cut by an occluder (``choose_arm_component``).

    Raises:
        ShapeError: the segmenter found no robot pixel (named as such, with the segmenter), and as
            ``reconstruct_shape``.
    """
    mask = segmenter(image)
    if not np.asarray(mask).any():
        raise ShapeError(f"the segmenter {segmenter!r} found no robot pixel in the image (is the arm in view?); "
                         f"try another segmenter or a mask of your own (docs/segmenters.md)")
    return reconstruct_shape(mask, robot, camera, config, base_pixel=base_pixel)


def render_shape_mask(result: ShapeResult, robot: ContinuumRobot) -> np.ndarray:
    """The fitted tube (the robot's own mesh) rendered binary at full resolution: ``(H, W)`` bool."""
    radii = torch.from_numpy(result.radii_m)[None]
    if result.pcc is not None:
        points, frames = result.pcc.points_frames(max(1, round((robot.n_rings - 1) / len(result.pcc.bends_rad))))
        faces = tube_faces(points.shape[1], robot.n_angles)
    else:
        control = torch.from_numpy(result.control_points_cam_m)[None]
        s = ring_parameters(robot.n_rings, dtype=torch.float64)
        points, frames = bezier_frames(control, s, robot.frame_method)
        faces = robot.faces()
    verts = tube_vertices(points, frames, radius_profile_at(radii, arc_length_fractions(points)), robot.n_angles)
    return render_hard(verts, faces, result.camera.K_tensor(), result.camera.image_size)[0].numpy()


def draw_shape_overlay(image: np.ndarray, result: ShapeResult, robot: ContinuumRobot) -> np.ndarray:
    """The fitted outline (green), centreline (red) and observed keypoints (yellow) on a copy of ``image``.

    Args:
        image: ``(H, W, 3)`` uint8 BGR, the undistorted image (or a mask drawn as grey, ``viz.gray_to_bgr``).
    """
    from pipeline import viz

    out = viz.draw_outline(image, render_shape_mask(result, robot))
    centre = result.centerline_cam_m @ result.camera.K_array().T
    out = viz.draw_polyline(out, centre[:, :2] / centre[:, 2:3])
    if len(result.keypoints_px):
        out = viz.draw_points(out, result.keypoints_px, labels=[str(j + 1) for j in range(len(result.keypoints_px))])
    return out


def _skeleton_loss_of(problem: "_FitProblem", params: dict[str, torch.Tensor]) -> torch.Tensor:
    return problem.skeleton_loss(params, 0)


def _rendered_loss_of(problem: "_FitProblem", params: dict[str, torch.Tensor]) -> torch.Tensor:
    return problem.loss(params, 0)


@functools.cache
def _compiled_loss_functions() -> tuple[Callable, Callable]:
    """``torch.compile`` of the two losses as functions of (problem, params), made once per process: a new problem
    (a new frame) reuses their graphs; its floats are not specialised (``specialize_float`` is off) and a second
    working-image size makes the size dynamic."""
    return torch.compile(_skeleton_loss_of), torch.compile(_rendered_loss_of)


_COMPILE_FAILED: list[str] = []  # the first failure's message: every later fit of the process runs uncompiled


def _compiled_losses(problem: "_FitProblem") -> tuple[Callable, Callable]:
    """``(skeleton loss, rendered loss)`` of ``problem`` as ``fit`` takes them, through ``torch.compile``; each
    falls back to the uncompiled loss (with one warning per process) where compiling fails."""
    compiled = _compiled_loss_functions()
    eager = (problem.skeleton_loss, problem.loss)

    def wrap(index: int) -> Callable:
        def loss(params: dict[str, torch.Tensor], iteration: int) -> torch.Tensor:
            if not _COMPILE_FAILED:
                try:
                    return compiled[index](problem, params)
                except Exception as error:  # no C++ compiler, an unsupported operation: fall back, once
                    _COMPILE_FAILED.append(f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}")
                    log.warning("shape fit: torch.compile failed (%s); the fit goes on uncompiled", _COMPILE_FAILED[0])
            return eager[index](params, iteration)
        return loss

    return wrap(0), wrap(1)


class _FitProblem:
    """The loss of the fit at the working resolution: tensors built once, the loss evaluated per iteration."""

    def __init__(self, observation: ShapeObservation, robot: ContinuumRobot, config: ShapeFitConfig,
                 dtype: torch.dtype, fixed_base: np.ndarray | None = None) -> None:
        self.fixed_base = None if fixed_base is None else torch.from_numpy(fixed_base)  # (2, 3) point, direction
        self.config = config
        self.robot = robot
        cam = observation.camera
        self.image_size = cam.image_size
        self.image_bounds = observation.image_bounds_px
        self.K = cam.K_tensor(dtype=dtype)
        self.mask = torch.from_numpy(observation.coverage).to(dtype)
        self.mask_area = float(observation.coverage.sum())
        self.path_length = observation.path_length_px
        self.targets = torch.from_numpy(observation.keypoints_px).to(dtype)  # (K, 2)
        self.fractions = torch.from_numpy(observation.keypoint_fractions).to(dtype)  # (K,)
        dense, dense_fractions = arc_length_keypoints(observation.path_px, SKELETON_POINTS)
        self.dense_targets = torch.from_numpy(dense).to(dtype)  # (D, 2) points along the whole path
        self.dense_fractions = torch.from_numpy(dense_fractions).to(dtype)  # (D,)
        path_fractions = polyline_arc_length(observation.path_px) / observation.path_length_px
        dense_radius = np.interp(dense_fractions, path_fractions, observation.radius_px)
        self.dense_radius = torch.from_numpy(dense_radius).to(dtype)  # (D,) apparent radius, pixels
        # The width term trusts the middle 80 % of the path (the ends are caps), wide parts more (r_px^2).
        weight = np.where((dense_fractions >= 0.1) & (dense_fractions <= 0.9), dense_radius**2, 0.0)
        self.dense_width_weight = torch.from_numpy(weight / max(weight.sum(), 1e-12)).to(dtype)  # (D,) sums to 1
        self.settings = SoftRasterSettings.from_sigma(config.sigma_px2)
        self.s = ring_parameters(config.render_rings, dtype=dtype)
        # PCC: about render_rings rings in all, evenly spaced in each section; lengths fixed or fitted.
        self.pcc_samples = max(1, round((config.render_rings - 1) / config.sections))
        rings = config.sections * self.pcc_samples + 1 if config.model == "pcc" else config.render_rings
        self.faces = tube_faces(rings, config.render_angles)
        self.pcc_lengths = PccLengths(total_m=robot.length_m, fixed_m=config.section_lengths_m)
        self.taper = robot.initial_radii_m(dtype=torch.float64)  # (n_rings,) at arc-length fractions j/(n-1)
        # A regular polygon of circumradius r has a mean projected width (n / pi) sin(pi / n) of the circle's.
        a = config.render_angles
        self.polygon_scale = (math.pi / a) / math.sin(math.pi / a)
        self.focal_px = math.sqrt(cam.fx * cam.fy)
        # working pixels the rendered outline grows by; (S, 1) per start once stacked (_stack_problems)
        self.rim_offset_px: float | torch.Tensor = float(observation.rim_offset_px)
        self.edge_offset_lookup = _EdgeOffsets(self.settings, a, dtype)
        self.per_start = False  # True once _stack_problems gave its per-frame fields a leading start dimension

    def astype(self, dtype: torch.dtype, *, skeleton_only: bool = False) -> "_FitProblem":
        """The same problem with its floating-point tensors in ``dtype`` (a copy; ``self`` where nothing changes).
        ``skeleton_only``: without the mask (``mask`` None; the copy evaluates the pre-fit's loss, not the rendered
        one), so that nothing image-sized is converted or, stacked, repeated (``_each_start_repeated``)."""
        if self.K.dtype == dtype and not skeleton_only:
            return self
        other = copy.copy(self)
        if skeleton_only:
            other.mask = None
        for name, value in vars(other).items():
            if torch.is_tensor(value) and value.is_floating_point():
                setattr(other, name, value.to(dtype))
        other.edge_offset_lookup = _EdgeOffsets(self.settings, self.config.render_angles, dtype)
        return other

    def control_points(self, state: torch.Tensor) -> torch.Tensor:
        """States ``(S, n+1, 3)`` -> control points ``(S, n+1, 3)`` (camera frame, metres), the base held when it
        is fixed: the first point at the base, the second on the base direction's ray, at least 1 mm out."""
        control = state_to_control_points(state)
        if self.fixed_base is None:
            return control
        base, direction = self.fixed_base.to(control)  # (3,), (3,)
        reach = ((control[:, 1] - base) * direction).sum(-1).clamp_min(1e-3)  # (S,) metres along the direction
        second = base + reach[:, None] * direction  # (S, 3)
        return torch.cat([base.expand(control.shape[0], 1, 3), second[:, None], control[:, 2:]], dim=1)

    def curve(self, params: dict[str, torch.Tensor], layout: Layout | None = None) -> tuple[torch.Tensor, Frames]:
        """Ring centres ``(S, R, 3)`` and frames of the states in ``params``: Bezier control points
        (``params["control"]``, ``control_points``: the base held when fixed) at ``render_rings`` parameters, or PCC
        sections (``params["base"]``, ``"rotation"``, ``"bend"``, ``"length_logits"``, ``pcc_state_to_parameters``)
        at ``pcc_samples`` points per section. With a ``layout`` (``_pad_states``), ``params["control"]`` holds
        curves of several orders, padded."""
        if self.config.model == "pcc":
            return pcc_points_frames(*pcc_state_to_parameters(params, self.pcc_lengths), self.pcc_samples)
        if layout is None:
            control = self.control_points(params["control"])  # (S, n+1, 3)
        else:
            control = [self.control_points(state) for state in _split_states(params["control"], layout)]
        return bezier_frames(control, self.s, self.robot.frame_method)

    def radii(self, offsets: torch.Tensor) -> torch.Tensor:
        """``(S, n_rings)`` radius offsets -> radii (metres), within ``radius_tolerance`` of the taper."""
        taper = self.taper.to(offsets)
        tolerance = self.config.radius_tolerance
        return torch.minimum(torch.maximum(taper + offsets, (1.0 - tolerance) * taper), (1.0 + tolerance) * taper)

    def edge_offsets(self, circle: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """The soft edge's offset ``(S, R)`` (working pixels, ``soft_edge_offset_px``) of rings of radii ``circle``
        ``(S, R)`` (metres) centred at ``points`` ``(S, R, 3)``: it depends on the ring's apparent radius and on how
        far apart the rings are in the image (the mean of the distances to its neighbours)."""
        with torch.no_grad():
            depth = points[..., 2].clamp_min(1e-9)
            apparent = circle * self.focal_px / depth
            centre = points[..., :2] / depth[..., None] * self.focal_px  # (S, R, 2) pixels, up to the offset
            gaps = (centre[:, 1:] - centre[:, :-1]).norm(dim=-1)  # (S, R-1)
            spacing = torch.cat([gaps[:, :1], 0.5 * (gaps[:, 1:] + gaps[:, :-1]), gaps[:, -1:]], dim=1)  # (S, R)
            return self.edge_offset_lookup(apparent, spacing)

    def render_radii(self, radii: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Radii of the rendered rings ``(S, R)`` from the radius profile ``(S, n_rings)`` (over arc length) and the
        ring centres ``(S, R, 3)``: interpolated at each ring's fraction of arc length, scaled to the polygon's mean
        width, shrunk by the soft edge's offset (``edge_offsets``, at the ring's depth) and grown by the mask's rim
        offset (``ShapeObservation.rim_offset_px``): drawn as the mask shows the arm.

        Returns:
            ``(rendered radii (S, R) metres, the offsets taken off (S, R) pixels: the edge's less the rim's)``.
        """
        if numba_path(points):  # one compiled call each way (``_radii_numba``)
            rim = self.rim_offset_px
            rim = (rim.detach().to(torch.float64).reshape(-1).numpy() if torch.is_tensor(rim)
                   else np.array([float(rim)]))
            lookup = self.edge_offset_lookup
            return RenderRadii.apply(points, radii, np.ascontiguousarray(np.broadcast_to(rim, (len(points),))),
                                     self.focal_px, self.polygon_scale, lookup.table64, lookup.radius_knots,
                                     lookup.spacing_knots)
        return self._render_radii_torch(radii, points)

    def _render_radii_torch(self, radii: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``render_radii`` as torch operations (any device; on CPU ``_radii_numba.RenderRadii`` gives the same to
        float rounding)."""
        circle = radius_profile_at(radii, arc_length_fractions(points))  # (S, R)
        offsets = self.edge_offsets(circle, points) - self.rim_offset_px  # grown by the mask's rim offset
        shrunk = circle * self.polygon_scale - offsets * points[..., 2] / self.focal_px
        return torch.maximum(shrunk, 0.1 * circle), offsets

    def loss(self, params: dict[str, torch.Tensor], iteration: int, layout: Layout | None = None) -> torch.Tensor:
        """The rendered fit's loss ``(S,)`` (module docstring, step 4) of states ``params["control"]``
        ``(S, n+1, 3)`` (curves of several orders with a ``layout``, ``_pad_states``) and radius offsets
        ``params["radius_offsets"]`` ``(S, n_rings)``."""
        fused = self._fused_loss()
        if fused and self._bezier_chain_applies(params, layout):
            state = params["control"]  # the whole chain from the states on in one node
            return BezierTubeLoss.apply(state, params["radius_offsets"], self._bezier_chain(state.shape[-2] - 1),
                                        self._tube_loss_terms_once(len(state)))
        points, frames = self.curve(params, layout)  # (S, R, 3)
        profile = self.radii(params["radius_offsets"])  # (S, n_rings)
        if fused and numba_path(points, profile):
            return TubeLoss.apply(points, frames.normal, frames.binormal, profile,
                                  self._tube_loss_terms_once(len(points)))
        radii, _ = self.render_radii(profile, points)  # (S, R)
        verts = tube_vertices(points, frames, radii, self.config.render_angles)
        silhouette = render_front_faces(verts, self.faces, self.K, self.image_size, self.settings)
        loss = self.config.w_mask * mask_loss(silhouette, self.mask) / self.mask_area
        if self.config.w_length > 0:
            loss = loss + self.config.w_length * self.length_term(points)
        if self.targets.shape[-2] and self.config.w_keypoint > 0:
            model, _ = self.model_keypoints(points, verts, self.fractions)  # (S, K, 2)
            distance = keypoint_loss(model, self.targets) / self.targets.shape[-2]
            loss = loss + self.config.w_keypoint * distance / self.path_length
        return loss

    def loss_and_gradients(self, params: dict[str, torch.Tensor], iteration: int):
        """``loss`` as ``optimize.fit`` takes it: where the Bezier chain applies, ``(losses (S,), gradients)`` computed
        without autograd (the same values as ``loss``'s node and its backward pass, a third of a millisecond less
        a step); elsewhere ``loss`` itself."""
        if not (self._fused_loss() and self._bezier_chain_applies(params, None)):
            return self.loss(params, iteration)
        state, offsets = params["control"], params["radius_offsets"]
        loss, saved = bezier_tube_loss(state, offsets, self._bezier_chain(state.shape[-2] - 1),
                                       self._tube_loss_terms_once(len(state)))

        def gradients(weights: torch.Tensor) -> dict[str, torch.Tensor]:
            g_state, g_offsets = bezier_tube_loss_gradients(saved, weights.numpy())
            return {"control": torch.from_numpy(g_state), "radius_offsets": torch.from_numpy(g_offsets)}

        return torch.from_numpy(loss).to(state.dtype), gradients

    def _fused_loss(self) -> bool:
        """Whether the rendered loss may take ``_tube_loss_numba``'s compiled nodes (``FUSED_LOSS``, the numba
        renderer)."""
        return FUSED_LOSS and self.settings.backend in ("auto", "numba")

    def _bezier_chain_applies(self, params: dict[str, torch.Tensor], layout: Layout | None) -> bool:
        """Whether ``_tube_loss_numba``'s Bezier chain (``BezierTubeLoss``, ``bezier_skeleton_terms``) takes these
        states: Bezier states of one order, the base free, rotation-minimising frames, CPU float32 or float64."""
        return (layout is None and self.config.model != "pcc" and self.fixed_base is None
                and self.robot.frame_method == "rmf" and numba_path(params["control"], params["radius_offsets"]))

    def _bezier_chain(self, order: int) -> BezierChain:
        """``BezierTubeLoss``'s chain for curves of ``order`` (the ring parameters ``s``, the taper)."""
        # built once per order and ring parameters, taper and tolerance (the same objects: a copy that replaced
        # one of them builds its own)
        key = (order, self.s, self.taper, self.config.radius_tolerance)
        chains = self.__dict__.setdefault("_chains", {})
        if key not in chains:
            chains[key] = BezierChain(weights=bezier_weights(order, tuple(self.s.tolist())), eps=FRENET_EPS,
                                      taper=self.taper.to(torch.float64).numpy(),
                                      tolerance=float(self.config.radius_tolerance))
        return chains[key]

    def _tube_loss_terms_once(self, starts: int) -> TubeLossTerms:
        """``tube_loss_terms(starts)``, built again only when one of the fields it reads is another object than at
        the last call (a copy of the problem, ``_stack_problems``, ``astype``, ``_each_start_repeated``, keeps the
        cache only while it shares every field)."""
        sources = (self.mask, self.mask_area, self.path_length, self.targets, self.fractions, self.K,
                   self.image_bounds, self.rim_offset_px, self.dense_targets, self.dense_fractions, self.dense_radius,
                   self.dense_width_weight, self.edge_offset_lookup, self.settings, self.config, self.faces)
        cached = self.__dict__.get("_terms_cache")  # (sources, {starts: terms})
        if cached is None or not all(a is b for a, b in zip(cached[0], sources)):
            cached = self._terms_cache = (sources, {})
        if starts not in cached[1]:
            cached[1][starts] = self.tube_loss_terms(starts)
        return cached[1][starts]

    def tube_loss_terms(self, starts: int) -> TubeLossTerms:
        """The fields ``loss`` compares ``starts`` tubes with, as ``_tube_loss_numba.TubeLoss`` takes them."""
        def per_start(value: float | torch.Tensor) -> np.ndarray:  # a float or (S,) / (S, 1) tensor -> (S,)
            array = value.detach().to(torch.float64).reshape(-1).numpy() if torch.is_tensor(value) else np.array(
                [float(value)])
            return np.ascontiguousarray(np.broadcast_to(array, (starts,)))

        def array(value: torch.Tensor) -> np.ndarray:
            return value.detach().to(torch.float64).numpy()

        lookup = self.edge_offset_lookup
        mask = None if self.mask is None else self.mask.detach()
        return TubeLossTerms(
            K=array(self.K), image_size=self.image_size, settings=self.settings,
            faces=self.faces.numpy(), angles=self.config.render_angles,
            mask=None if mask is None else mask.reshape(-1, *mask.shape[-2:]).contiguous().numpy(),
            mask_area=per_start(self.mask_area),
            path_length=per_start(self.path_length), targets=array(self.targets), fractions=array(self.fractions),
            image_bounds=np.asarray(self.image_bounds, dtype=np.float64), rim=per_start(self.rim_offset_px),
            focal=self.focal_px, polygon_scale=self.polygon_scale, table=lookup.table64,
            radius_knots=lookup.radius_knots, spacing_knots=lookup.spacing_knots,
            dense_targets=array(self.dense_targets), dense_fractions=array(self.dense_fractions),
            dense_radius=array(self.dense_radius), dense_width_weight=array(self.dense_width_weight),
            length_m=self.robot.length_m, w_mask=self.config.w_mask, w_length=self.config.w_length,
            w_keypoint=self.config.w_keypoint, w_width=self.config.w_width)

    def skeleton_loss(self, params: dict[str, torch.Tensor], iteration: int,
                      layout: Layout | None = None) -> torch.Tensor:
        """The pre-fit's loss ``(S,)`` (no rendering): the projected centreline against ``SKELETON_POINTS`` points
        along the skeleton path (mean distance over the path length, like the keypoint term), the length term and
        the width term (``ShapeFitConfig.w_width``); ``layout`` as for ``loss``."""
        if FUSED_LOSS and numba_path(*params.values()):
            points, frames = self.curve(params, layout)  # (S, R, 3)
            profile = self.radii(params["radius_offsets"])  # (S, n_rings)
            return SkeletonLoss.apply(points, frames.normal, frames.binormal, profile,
                                      self._tube_loss_terms_once(len(points)))
        return self.skeleton_loss_of_terms(*self.skeleton_terms(params, layout))

    def skeleton_terms(self, params: dict[str, torch.Tensor], layout: Layout | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The pre-fit's residuals of states ``params`` (as ``skeleton_loss``): the model's points at the
        skeleton points' fractions ``(S, D, 2)`` pixels, their apparent radii relative to the mask's, minus 1,
        ``(S, D)``, and the centreline's relative length error ``(l - L) / L`` ``(S,)``."""
        if FUSED_LOSS and not torch.is_grad_enabled() and self._bezier_chain_applies(params, layout):
            state = params["control"]  # the pre-fit's Levenberg-Marquardt: the whole chain compiled
            return bezier_skeleton_terms(state, params["radius_offsets"], self._bezier_chain(state.shape[-2] - 1),
                                         self._tube_loss_terms_once(len(state)))
        points, frames = self.curve(params, layout)  # (S, R, 3)
        radii, offsets = self.render_radii(self.radii(params["radius_offsets"]), points)  # (S, R), (S, R)
        if FUSED_LOSS and not torch.is_grad_enabled() and numba_path(points):  # the pre-fit's Levenberg-Marquardt
            centre, ends, apparent = tube_outline(points, frames.normal, frames.binormal, radii, offsets, self.K,
                                                  self.config.render_angles)
            model, model_radius = PathPoints.apply(centre, ends, apparent[..., None],
                                                   np.asarray(self.image_bounds, dtype=np.float64),
                                                   self.dense_fractions.to(torch.float64).numpy())
        else:
            verts = tube_vertices(points, frames, radii, self.config.render_angles)
            apparent = self.apparent_radii(points, verts, offsets)  # (S, R) pixels
            model, model_radius = self.model_keypoints(points, verts, self.dense_fractions, apparent[..., None])
        relative = model_radius[..., 0] / self.dense_radius - 1.0  # (S, D)
        return model, relative, self.length_error(points)

    def skeleton_loss_of_terms(self, model: torch.Tensor, relative: torch.Tensor, length: torch.Tensor
                               ) -> torch.Tensor:
        """``skeleton_loss`` ``(S,)`` from ``skeleton_terms``' residuals."""
        loss = keypoint_loss(model, self.dense_targets) / (self.dense_targets.shape[-2] * self.path_length)
        width = (self.dense_width_weight * relative * relative).sum(-1)
        return loss + self.config.w_length * length * length + self.config.w_width * width

    def apparent_radii(self, points: torch.Tensor, verts: torch.Tensor, edge_offsets: torch.Tensor) -> torch.Tensor:
        """The tube's half-width in the image at each ring, ``(S, R)`` pixels: half the extent of the projected ring
        across the projected centreline (exact under perspective, also for rings seen obliquely), plus the soft
        edge offsets ``(S, R)`` that ``render_radii`` took off (so it is the modelled tube's, not the shrunk mesh's)."""
        S, R, _ = points.shape
        A = self.config.render_angles
        centre = project_points(points, self.K)  # (S, R, 2)
        rings = project_points(verts[:, : R * A], self.K).reshape(S, R, A, 2)
        forward = torch.cat([centre[:, 1:2] - centre[:, :1], centre[:, 2:] - centre[:, :-2],
                             centre[:, -1:] - centre[:, -2:-1]], dim=1)  # (S, R, 2) central differences
        normal = torch.stack([-forward[..., 1], forward[..., 0]], dim=-1)
        normal = normal * torch.rsqrt((normal * normal).sum(-1, keepdim=True) + 1e-12)
        across = ((rings - centre[:, :, None]) * normal[:, :, None]).sum(-1)  # (S, R, A)
        return 0.5 * (across.amax(-1) - across.amin(-1)) + edge_offsets

    def length_term(self, points: torch.Tensor) -> torch.Tensor:
        """``((l - L) / L)^2`` with ``l`` the length of the polyline through the ring centres ``(S, R, 3)``."""
        error = self.length_error(points)
        return error * error

    def length_error(self, points: torch.Tensor) -> torch.Tensor:
        """``(l - L) / L`` ``(S,)`` with ``l`` the length of the polyline through the ring centres ``(S, R, 3)``."""
        step = points[:, 1:] - points[:, :-1]  # (S, R-1, 3)
        length = torch.sqrt((step * step).sum(-1) + 1e-18).sum(-1)  # (S,) metres
        return (length - self.robot.length_m) / self.robot.length_m

    def model_keypoints(
        self, points: torch.Tensor, verts: torch.Tensor, fractions: torch.Tensor, attributes: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Model points at ``fractions`` ``(K,)`` of the projected centreline's visible length: ``(S, K, 2)``.

        The model path is the projected ring centres, extended at each end to the outer edge of the cap (the
        farthest projected vertex of the end ring along the path direction), like the skeleton path. Only its
        segments whose middle lies in the image count (the observed path is cut by the border too).

        Args:
            points: ``(S, R, 3)`` ring centres; verts: the tube's vertices (ring-major).
            fractions: ``(K,)`` in (0, 1].
            attributes: optional ``(S, R, C)`` per-ring values, interpolated at the same places.

        Returns:
            ``(points (S, K, 2), attributes at them (S, K, C) or None)``.
        """
        S, R, _ = points.shape
        A = self.config.render_angles
        centre = project_points(points, self.K)  # (S, R, 2)
        ends = torch.cat([verts[:, :A], verts[:, (R - 1) * A : R * A]], dim=1)  # (S, 2A, 3) base and tip rings
        rings = project_points(ends, self.K).reshape(S, 2, A, 2)
        if numba_path(centre):  # one compiled call each way (``_path_numba``)
            values = centre.new_zeros(S, R, 0) if attributes is None else attributes
            located, at = PathPoints.apply(centre, rings, values, np.asarray(self.image_bounds, dtype=np.float64),
                                           fractions.detach().to(torch.float64).numpy())
            return located, (None if attributes is None else at)
        return _path_points_torch(centre, rings, self.image_bounds, fractions, attributes)


def _path_points_torch(centre: torch.Tensor, rings: torch.Tensor, image_bounds: tuple[float, float, float, float],
                       fractions: torch.Tensor, attributes: torch.Tensor | None
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``_FitProblem.model_keypoints`` from the projected ring centres ``(S, R, 2)`` and end rings ``(S, 2, A, 2)``
    as torch operations (any device; on CPU ``_path_numba.PathPoints`` gives the same to float rounding)."""
    S, R, _ = centre.shape
    base = _cap_edge(centre[:, 0], centre[:, 1], rings[:, 0])  # (S, 2)
    tip = _cap_edge(centre[:, -1], centre[:, -2], rings[:, 1])
    path = torch.cat([base[:, None], centre, tip[:, None]], dim=1)  # (S, R+2, 2)
    u_min, v_min, u_max, v_max = image_bounds
    segment = path[:, 1:] - path[:, :-1]  # (S, R+1, 2)
    length = torch.sqrt((segment * segment).sum(-1) + 1e-12)  # (S, R+1)
    with torch.no_grad():
        middle = 0.5 * (path[:, 1:] + path[:, :-1])
        visible = ((middle[..., 0] >= u_min) & (middle[..., 0] <= u_max)
                   & (middle[..., 1] >= v_min) & (middle[..., 1] <= v_max)).to(length.dtype)
    cum = torch.cat([length.new_zeros(S, 1), torch.cumsum(length * visible, dim=1)], dim=1)  # (S, R+2)
    target = fractions[None] * cum[:, -1:]  # (S, K)
    upper = torch.searchsorted(cum.detach().contiguous(), target.detach().contiguous(), side="left")
    upper = upper.clamp(1, R + 1)  # (S, K) index of the segment's end point
    lower = upper - 1
    c0, c1 = cum.gather(1, lower), cum.gather(1, upper)
    span = c1 - c0
    safe = torch.where(span > 0, span, torch.ones_like(span))
    t = torch.where(span > 0, (target - c0) / safe, torch.ones_like(span)).clamp(0.0, 1.0)[..., None]

    def lerp(values: torch.Tensor) -> torch.Tensor:  # (S, R+2, C) -> (S, K, C)
        C = values.shape[-1]
        v0 = values.gather(1, lower[..., None].expand(S, -1, C))
        v1 = values.gather(1, upper[..., None].expand(S, -1, C))
        return v0 + t * (v1 - v0)

    located = lerp(path)
    if attributes is None:
        return located, None
    padded = torch.cat([attributes[:, :1], attributes, attributes[:, -1:]], dim=1)  # cap edges: end rings
    return located, lerp(padded)


@dataclass(frozen=True, kw_only=True)
class PccParameters:
    """A fitted piecewise-constant-curvature centreline (``pipeline.shapes.pcc``), camera frame, metres, radians.

    Fields:
        base_cam_m: ``(3,)`` base point.
        R_cam_base: ``(3, 3)`` base frame: columns body x, body y, and body z = the tangent leaving the base.
        bends_rad: ``(N, 2)`` bend vectors ``(b_x, b_y)``: section ``i`` turns its tangent by ``|b_i|`` radians
            towards ``(b_x, b_y, 0)`` of the frame it starts in (the frame the previous section ends in; the base
            frame for the first), the frame carried along without twist.
        section_lengths_m: ``(N,)``, summing to the robot's length.
    """

    base_cam_m: np.ndarray
    R_cam_base: np.ndarray
    bends_rad: np.ndarray
    section_lengths_m: np.ndarray

    @property
    def curvatures_per_m(self) -> np.ndarray:
        """``(N,)`` curvature of each section ``|b_i| / L_i``, 1/m."""
        return bend_to_curvature_plane(torch.from_numpy(self.bends_rad), torch.from_numpy(self.section_lengths_m))[
            0].numpy()

    @property
    def plane_angles_rad(self) -> np.ndarray:
        """``(N,)`` bending-plane angle of each section ``atan2(b_y, b_x)`` in the frame it starts in (0 if
        straight)."""
        return bend_to_curvature_plane(torch.from_numpy(self.bends_rad), torch.from_numpy(self.section_lengths_m))[
            1].numpy()

    def points(self, samples_per_section: int) -> np.ndarray:
        """``(N m + 1, 3)`` centreline points, ``m`` evenly spaced per section (see ``pcc_points_frames``)."""
        return self.points_frames(samples_per_section)[0][0].numpy()

    def points_frames(self, samples_per_section: int) -> tuple[torch.Tensor, Frames]:
        """``pcc_points_frames`` of these sections, float64, batch of one."""
        return pcc_points_frames(torch.from_numpy(self.base_cam_m)[None], torch.from_numpy(self.R_cam_base)[None],
                                 torch.from_numpy(self.bends_rad)[None], torch.from_numpy(self.section_lengths_m)[None],
                                 samples_per_section)

    def to_dict(self) -> dict:
        """The result file's ``"pcc"`` entry."""
        return {"base_cam_m": self.base_cam_m, "R_cam_base": self.R_cam_base, "bend_vectors_rad": self.bends_rad,
                "curvatures_per_m": self.curvatures_per_m, "plane_angles_rad": self.plane_angles_rad,
                "section_lengths_m": self.section_lengths_m}


@dataclass(frozen=True, kw_only=True)
class PccLengths:
    """Section lengths of the PCC fit: ``fixed_m`` (scaled to sum to ``total_m``), or, when empty, ``total_m``
    times the softmax of the state's ``length_logits`` (free lengths under the known total)."""

    total_m: float
    fixed_m: tuple[float, ...] = ()

    def __call__(self, logits: torch.Tensor) -> torch.Tensor:
        """``(S, N)`` logits -> ``(S, N)`` lengths, metres."""
        if self.fixed_m:
            fixed = torch.tensor(self.fixed_m, dtype=logits.dtype, device=logits.device)
            return (fixed * (self.total_m / float(sum(self.fixed_m)))).expand_as(logits)
        return self.total_m * torch.softmax(logits, dim=-1)


def pcc_state_to_parameters(
    params: dict[str, torch.Tensor], lengths: PccLengths
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The PCC fit's state -> ``(base (S, 3), R_base (S, 3, 3), bends (S, N, 2), lengths (S, N))``.

    State: ``params["base"]`` ``(S, 3)`` the base point as ``(x / z, y / z, ln z)`` (like
    ``control_points_to_state``), ``"rotation"`` ``(S, 6)`` the base frame's 6D representation
    (its first two columns, ``rotation_from_6d``), ``"bend"`` ``(S, N, 2)`` bend vectors (radians), ``"length_logits"`` ``(S, N)``.
    """
    base = state_to_control_points(params["base"][:, None])[:, 0]
    return base, rotation_from_6d(params["rotation"]), params["bend"], lengths(params["length_logits"])


#: The most residual evaluations of the least-squares fit of PCC sections to a centreline
#: (``_sections_fitted_to_curves``).
PCC_FIT_EVALUATIONS = 150


def _pcc_initial_state(curves: torch.Tensor, sections: int, lengths: PccLengths,
                       iterations: int = PCC_FIT_EVALUATIONS,
                       base_frame: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, torch.Tensor]:
    """PCC states ``(S, ...)`` close to centrelines ``(S, P, 3)`` (float64, uniform in arc length, base first).

    Closed form first: the tangents of each section's arc through the curve's points at the section's start,
    middle and end (the two half-chords turn by half the arc's bend; exact on an arc, and blind to a hook of the
    curve near the base, which first differences would take for the base's direction: a fitted Bezier curve of
    a tracked video had one, 12 mm long); the base frame's z is the first section's start tangent, and each
    section's bend vector turns the frame's z onto the section's end tangent (its bend is the angle between the
    tangents, in the plane they span). Then fitted to the curve by least squares (``_sections_fitted_to_curves``,
    at most ``iterations`` evaluations). With ``base_frame`` (base points ``(S, 3)`` and frames ``(S, 3, 3)``)
    the base is that, held by the least squares too.
    """
    S, P, _ = curves.shape
    dtype = curves.dtype
    logits = torch.zeros(S, sections, dtype=dtype)
    section_lengths = lengths(logits)  # (S, N)
    ends = torch.cumsum(section_lengths, 1) / section_lengths.sum(1, keepdim=True)  # (S, N) section end fractions
    starts = ends - section_lengths / section_lengths.sum(1, keepdim=True)
    start_point, middle, end_point = (_along_curves(f, curves) for f in (starts, 0.5 * (starts + ends), ends))
    first, second = unit(middle - start_point), unit(end_point - middle)  # the half-chords
    axis = torch.linalg.cross(first, second, dim=-1)
    half = torch.atan2(torch.linalg.norm(axis, dim=-1), (first * second).sum(-1))  # (S, N) half the bend
    axis = unit(axis)  # 0 on a straight section: no turn
    tangents = _turned(second, axis, 0.5 * half)  # (S, N, 3) each section's end tangent
    if base_frame is None:
        base = curves[:, 0]
        z = _turned(first[:, 0], axis[:, 0], -0.5 * half[:, 0])  # the base's tangent
        x = initial_normal(z, torch.zeros_like(z))  # a perpendicular
        frame = torch.stack([x, torch.linalg.cross(z, x, dim=-1), z], dim=-1)  # (S, 3, 3) columns x, y, z
    else:
        base, frame = (value.to(dtype).expand(S, *value.shape[1:]) for value in base_frame)
    R_base = frame
    bends = []
    for i in range(sections):
        v = torch.einsum("sji,sj->si", frame, tangents[:, i])  # the end tangent in the section's frame
        sideways = torch.linalg.norm(v[:, :2], dim=-1)
        angle = torch.atan2(sideways, v[:, 2])
        direction = torch.where(sideways[:, None] > 1e-9, v[:, :2] / sideways.clamp_min(1e-9)[:, None],
                                torch.zeros_like(v[:, :2]))
        bend = angle[:, None] * direction  # (S, 2)
        bends.append(bend)
        _, frames = pcc_points_frames(torch.zeros(S, 3, dtype=dtype), frame, bend[:, None],
                                      section_lengths[:, i:i + 1], 1)
        frame = torch.stack([frames.normal[:, -1], frames.binormal[:, -1], frames.tangent[:, -1]], dim=-1)
    state = {"base": control_points_to_state(base[:, None])[:, 0], "rotation": rotation_to_6d(R_base),
             "bend": torch.stack(bends, 1), "length_logits": logits}
    return _sections_fitted_to_curves(state, curves, lengths, iterations, hold_base=base_frame is not None)


def _sections_fitted_to_curves(state: dict[str, torch.Tensor], curves: torch.Tensor, lengths: PccLengths,
                               iterations: int, *, hold_base: bool = False) -> dict[str, torch.Tensor]:
    """PCC states ``(S, ...)`` fitted to centrelines ``(S, P, 3)``: the least-squares distance between their points
    (8 per section) and the curves' at the same arc-length fractions, by Levenberg-Marquardt
    (``scipy.optimize.least_squares``, at most ``iterations`` evaluations, the Jacobian by forward differences in
    one batch) on each start's base state, a rotation vector turning its base frame and its bends; its section
    lengths held (free, they let a short first section curl up near the base where the points barely count: a
    section of 12 mm bent by 4 rad, seen on a tracked video); with ``hold_base`` its bends alone. The states as
    they are for 0 steps (no rendering)."""
    if iterations == 0:
        return state
    from scipy.optimize import least_squares

    dtype = curves.dtype
    N = state["bend"].shape[1]
    samples = 8
    out = {name: value.clone() for name, value in state.items()}
    for i in range(len(curves)):
        R0 = rotation_from_6d(state["rotation"][i:i + 1].to(torch.float64))  # (1, 3, 3)
        base0 = state["base"][i:i + 1].to(torch.float64)
        x0 = torch.cat([*([] if hold_base else [base0[0], torch.zeros(3, dtype=torch.float64)]),
                        state["bend"][i].reshape(-1).to(torch.float64)]).numpy()
        section_lengths = lengths(state["length_logits"][i:i + 1].to(torch.float64))  # (1, N), held

        def unpack(x: torch.Tensor) -> tuple[torch.Tensor, ...]:  # (B, p) -> base state, R, bends
            if hold_base:
                return base0.expand(len(x), -1), R0.expand(len(x), -1, -1), x.reshape(-1, N, 2)
            return x[:, :3], R0 @ rotvec_to_rotmat(x[:, 3:6]), x[:, 6:].reshape(-1, N, 2)

        curve = curves[i:i + 1].to(torch.float64)
        target = _along_curves(pcc_section_fractions(section_lengths, samples), curve)  # (1, M/3, 3)

        def residuals(x: torch.Tensor) -> torch.Tensor:  # (B, p) -> (B, M)
            base_state, R, bends = unpack(x)
            points, _ = pcc_points_frames(state_to_control_points(base_state[:, None])[:, 0], R, bends,
                                          section_lengths.expand(len(x), -1), samples)
            return ((points - target) / lengths.total_m).reshape(len(x), -1)

        def fun(x: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return residuals(torch.from_numpy(x)[None])[0].numpy()

        def jac(x: np.ndarray) -> np.ndarray:
            step = 1e-6
            probes = torch.from_numpy(x)[None] + torch.cat([torch.zeros(1, len(x), dtype=torch.float64),
                                                            step * torch.eye(len(x), dtype=torch.float64)])
            with torch.no_grad():
                r = residuals(probes)
            return ((r[1:] - r[:1]) / step).T.numpy()

        x = least_squares(fun, x0, jac=jac, method="lm", max_nfev=iterations).x
        base_state, R, bends = unpack(torch.from_numpy(x)[None])
        out["base"][i] = base_state[0].to(dtype)
        out["rotation"][i] = rotation_to_6d(R)[0].to(dtype)
        out["bend"][i] = bends[0].to(dtype)
    return out


def _turned(v: torch.Tensor, axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Vectors ``(..., 3)`` turned by ``angle`` ``(...)`` about unit axes ``(..., 3)``."""
    R = rotvec_to_rotmat((axis * angle[..., None]).reshape(-1, 3))
    return (R @ v.reshape(-1, 3, 1)).reshape(v.shape)


def _along_curves(fractions: torch.Tensor, curves: torch.Tensor) -> torch.Tensor:
    """Points of polylines ``(S, P, 3)`` at arc-length fractions ``(S, K)`` of each (linear between their points):
    ``(S, K, 3)``."""
    step = curves[:, 1:] - curves[:, :-1]
    cum = torch.cat([torch.zeros_like(step[:, :1, 0]), torch.cumsum(torch.linalg.norm(step, dim=-1), 1)], 1)
    frac = (cum / cum[:, -1:]).numpy()  # (S, P)
    out = [torch.stack([torch.from_numpy(np.interp(fractions[i].numpy(), frac[i], curves[i, :, d].numpy()))
                        for d in range(3)], -1) for i in range(len(curves))]
    return torch.stack(out).to(curves.dtype)


def render_front_faces(
    verts_cam: torch.Tensor,
    faces: torch.Tensor,
    K: torch.Tensor,
    image_size: tuple[int, int],
    settings: SoftRasterSettings,
) -> torch.Tensor:
    """Soft silhouettes ``(B, H, W)`` of closed, outward-wound meshes ``(B, V, 3)`` from their front faces only.

    A closed surface's silhouette is covered by the faces turned towards the camera (``n . c < 0`` for the face
    normal ``n`` and a corner ``c``, camera frame), so the others are left out
    (``SoftRasterSettings.cull_back_faces``: by their winding on the screen, in the rasterizer's face set-up):
    half the rasterizer's work. The tube of ``pipeline.shapes.tube`` is such a mesh.
    """
    culling = settings if settings.cull_back_faces else dataclasses.replace(settings, cull_back_faces=True)
    return render_silhouette(verts_cam, faces, K, image_size, culling)


#: Apparent tube radii (pixels of the working image) at which ``soft_edge_offsets_px`` calibrates the offset.
EDGE_CALIBRATION_RADII_PX = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0)

#: Distances between rings in the image (working pixels) at which ``soft_edge_offsets_px`` calibrates the offset.
EDGE_CALIBRATION_SPACINGS_PX = (1.5, 3.0, 6.0, 12.0, 24.0)


#: ``calibrate_soft_edge_offsets`` for the fit's defaults (``sigma_px2`` 0.25, 16 vertices per ring), so that a
#: fit with them does not spend a second on it; ``tests/test_shape_estimation.py`` checks it against a fresh
#: calibration. Rows: ``EDGE_CALIBRATION_RADII_PX``; columns: ``EDGE_CALIBRATION_SPACINGS_PX``; pixels.
DEFAULT_EDGE_OFFSETS_PX = (
    (0.7008, 0.6523, 0.6254, 0.6161, 0.6052),
    (0.6572, 0.6084, 0.5775, 0.5675, 0.5559),
    (0.6115, 0.5570, 0.5276, 0.5178, 0.5041),
    (0.5834, 0.5282, 0.4948, 0.4833, 0.4701),
    (0.5532, 0.4941, 0.4452, 0.4232, 0.4089),
    (0.5338, 0.4525, 0.3941, 0.3759, 0.3424),
    (0.5088, 0.4254, 0.3376, 0.3080, 0.2684),
    (0.4965, 0.3788, 0.3032, 0.2774, 0.2355),
    (0.4847, 0.3593, 0.2694, 0.2333, 0.1868),
    (0.4864, 0.3550, 0.2565, 0.2248, 0.1731),
    (0.5162, 0.3878, 0.2819, 0.2479, 0.1912),
)

#: (sigma_px2, vertices per ring) of ``DEFAULT_EDGE_OFFSETS_PX``.
DEFAULT_EDGE_OFFSETS_FOR = (0.25, 16)


@functools.lru_cache(maxsize=32)
def soft_edge_offsets_px(settings: SoftRasterSettings, n_angles: int) -> np.ndarray:
    """``calibrate_soft_edge_offsets(settings, n_angles)``, cached per arguments; ``DEFAULT_EDGE_OFFSETS_PX`` for
    the fit's default settings."""
    sigma_px2, angles = DEFAULT_EDGE_OFFSETS_FOR
    if settings == SoftRasterSettings.from_sigma(sigma_px2) and n_angles == angles:
        return np.array(DEFAULT_EDGE_OFFSETS_PX)
    return calibrate_soft_edge_offsets(settings, n_angles)


def calibrate_soft_edge_offsets(settings: SoftRasterSettings, n_angles: int) -> np.ndarray:
    """How far (pixels) the soft silhouette of a tube's side reaches beyond its hard silhouette, as the mask loss
    sees it, per apparent radius (``EDGE_CALIBRATION_RADII_PX``) and distance between rings in the image
    (``EDGE_CALIBRATION_SPACINGS_PX``).

    ``S = 1 - prod_f (1 - p_f)`` unites every face near a tube's contour (the sides seen edge-on), so the soft
    silhouette is wider than the tube, by an amount that depends on the softness and on how many faces crowd
    near a contour pixel: more for thin tubes and closely spaced rings (with ``sigma_px2`` 0.25 and 16 vertices
    per ring: 0.67 px at a radius of 1.5 px and rings 1.5 px apart, 0.19 px at 48 px and 24 px). Measured here
    for the settings at hand: a straight tube seen side-on, near orthographically (f = 1000 px), whose pixel
    coverage (a hard render with 64 vertices per ring at 4x the resolution, area-averaged, like the fit's target)
    is the target; the rendered radius is ``r`` times the polygon's mean-width scale (``_FitProblem``) minus ``d``;
    the mismatch ``sum (S - M)^2`` over the side (the caps left out), summed over 4 rolls of the ring polygon (a
    quarter of its step apart) and 2 sub-pixel positions, is evaluated for ``d`` on a 0.08 px grid in one batched
    render, and its minimum refined by a parabola through the lowest grid point and its neighbours. About 1-2 s
    (``soft_edge_offsets_px`` caches it).

    Returns:
        ``(len(EDGE_CALIBRATION_RADII_PX), len(EDGE_CALIBRATION_SPACINGS_PX))`` offsets ``d >= 0`` (pixels); the fit
        renders a ring of radius ``r`` (metres) at depth ``z`` with radius ``r - d z / f`` (``soft_edge_offset_px``).
    """
    f, fine, length, step = 1000.0, 4, 48.0, 0.08  # length: the tube's side, px
    scale = (math.pi / n_angles) / math.sin(math.pi / n_angles)
    grid = torch.arange(0.0, 2.5 * math.sqrt(settings.sigma_px2) + 0.4, step, dtype=torch.float64)  # (D,) px
    margin = int(math.ceil(settings.cutoff_px)) + 4
    table = np.zeros((len(EDGE_CALIBRATION_RADII_PX), len(EDGE_CALIBRATION_SPACINGS_PX)))
    for j, spacing_px in enumerate(EDGE_CALIBRATION_SPACINGS_PX):
        rings = int(round(length / spacing_px)) + 1
        faces, exact_faces = tube_faces(rings, n_angles), tube_faces(rings, 64)
        x = torch.linspace(-length / 2 / f, length / 2 / f, rings, dtype=torch.float64)
        tangent = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(1, rings, 3)
        for i, radius_px in enumerate(EDGE_CALIBRATION_RADII_PX):
            W, H = int(length) + 2 * margin, int(2 * radius_px) + 2 * margin
            K = torch.tensor([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
            K_fine = K.clone()
            K_fine[:2] *= fine
            K_fine[:2, 2] += (fine - 1) / 2  # pixel centres at integers in both images
            side = slice(int(W / 2 - length / 2) + 8, int(W / 2 + length / 2) - 8)  # columns away from the caps
            meshes, targets = [], []
            for roll in range(4):
                angle = 2.0 * math.pi / n_angles * roll / 4
                normal = torch.tensor([0.0, math.cos(angle), math.sin(angle)], dtype=torch.float64).expand(1, rings, 3)
                frames = Frames(tangent, normal, torch.linalg.cross(tangent, normal, dim=-1))
                for shift_px in (0.0, 0.5):
                    points = torch.stack([x, torch.full_like(x, shift_px / f), torch.ones_like(x)], -1)[None]
                    exact = tube_vertices(points, frames, torch.full((1, rings), radius_px / f, dtype=torch.float64),
                                          64)
                    hard = render_hard(exact, exact_faces, K_fine, (H * fine, W * fine))[0]
                    targets.append(hard.to(torch.float64).reshape(H, fine, W, fine).mean(dim=(1, 3)))
                    radii = (radius_px * scale - grid[:, None].expand(-1, rings)) / f  # (D, R)
                    meshes.append(tube_vertices(points.expand(len(grid), -1, -1), Frames(*(
                        v.expand(len(grid), -1, -1) for v in frames)), radii.clamp_min(0.05 * radius_px / f),
                        n_angles))  # (D, V, 3)
            silhouettes = render_front_faces(torch.cat(meshes), faces, K, (H, W), settings)  # (8 D, H, W)
            target = torch.stack(targets).repeat_interleave(len(grid), dim=0)  # (8 D, H, W)
            mismatch = ((silhouettes - target)[..., side] ** 2).sum(dim=(1, 2)).reshape(len(targets), -1).sum(0)
            k = int(torch.argmin(mismatch).clamp(1, len(grid) - 2))
            a, b, c = (float(v) for v in mismatch[k - 1:k + 2])
            curvature = a - 2.0 * b + c
            shift = 0.5 * (a - c) / curvature if curvature > 0 else 0.0
            table[i, j] = max(float(grid[k]) + step * max(min(shift, 1.0), -1.0), 0.0)
    return table


def soft_edge_offset_px(settings: SoftRasterSettings, n_angles: int, radius_px: torch.Tensor,
                        spacing_px: torch.Tensor) -> torch.Tensor:
    """The soft edge's offset (pixels, ``soft_edge_offsets_px``) of rings of apparent radii ``radius_px`` and
    distances between rings in the image ``spacing_px`` (pixels, the same shape): bilinear in the logarithms of
    both between the calibrated values, held at the table's ends outside them. Not differentiated (the offset is
    a correction; its gradient through the radius and spacing is left out)."""
    return _EdgeOffsets(settings, n_angles, radius_px.dtype, radius_px.device)(radius_px, spacing_px)


class _EdgeOffsets:
    """``soft_edge_offset_px`` with its table and knots as tensors, built once (the fit looks it up every step)."""

    def __init__(self, settings: SoftRasterSettings, n_angles: int, dtype: torch.dtype,
                 device: torch.device | None = None) -> None:
        self.table64 = np.ascontiguousarray(soft_edge_offsets_px(settings, n_angles), dtype=np.float64)  # (I, J)
        self.radius_knots = np.array(EDGE_CALIBRATION_RADII_PX, dtype=np.float64)
        self.spacing_knots = np.array(EDGE_CALIBRATION_SPACINGS_PX, dtype=np.float64)
        table = torch.as_tensor(self.table64, dtype=dtype, device=device)
        self.flat, self.width = table.reshape(-1).clone(), table.shape[1]
        self.radii = (EDGE_CALIBRATION_RADII_PX, torch.tensor(EDGE_CALIBRATION_RADII_PX, dtype=dtype,
                                                               device=device).log())
        self.spacings = (EDGE_CALIBRATION_SPACINGS_PX, torch.tensor(EDGE_CALIBRATION_SPACINGS_PX, dtype=dtype,
                                                                     device=device).log())

    @staticmethod
    def _locate(values: torch.Tensor, knots: tuple[tuple[float, ...], torch.Tensor]
                ) -> tuple[torch.Tensor, torch.Tensor]:
        bounds, logs = knots
        x = values.detach().clamp(bounds[0], bounds[-1]).log()
        upper = torch.searchsorted(logs, x.contiguous()).clamp(1, len(bounds) - 1)
        return upper, (x - logs[upper - 1]) / (logs[upper] - logs[upper - 1])

    def __call__(self, radius_px: torch.Tensor, spacing_px: torch.Tensor) -> torch.Tensor:
        i, t = self._locate(radius_px, self.radii)
        j, u = self._locate(spacing_px, self.spacings)
        flat, width = self.flat, self.width
        low = flat[(i - 1) * width + j - 1] * (1 - u) + flat[(i - 1) * width + j] * u
        high = flat[i * width + j - 1] * (1 - u) + flat[i * width + j] * u
        return (low + t * (high - low)).detach()


Layout = tuple[tuple[int, int], ...]  # (Bezier order, count) of each group of a padded batch of states, in turn


def _pad_states(groups: Sequence[torch.Tensor]) -> tuple[torch.Tensor, Layout]:
    """States of curves of several orders ``[(S_i, n_i+1, 3)]`` -> one batch ``(sum S_i, max n_i + 1, 3)`` and its
    layout. A shorter state is padded with copies of its last control point: padding takes no part in any loss, so
    its gradient is zero and Adam (element-wise) leaves it, and each curve's steps are the ones it would take alone.
    """
    width = max(group.shape[1] for group in groups)
    padded = [torch.cat([group, group[:, -1:].expand(-1, width - group.shape[1], -1)], dim=1) for group in groups]
    return torch.cat(padded), tuple((group.shape[1] - 1, group.shape[0]) for group in groups)


def _split_states(padded: torch.Tensor, layout: Layout) -> list[torch.Tensor]:
    """Inverse of ``_pad_states``: ``[(S_i, n_i+1, 3)]``, views of ``padded``."""
    groups, first = [], 0
    for order, count in layout:
        groups.append(padded[first:first + count, : order + 1])
        first += count
    return groups


def control_points_to_state(control_points: torch.Tensor) -> torch.Tensor:
    """The fit's state ``(S, n+1, 3)``: each control point as ``(x / z, y / z, ln z)`` (its ray and log depth).

    Adam moves each coordinate by about its learning rate per step; in these coordinates a step moves a control
    point's image position and its depth independently (in the camera frame, a depth change alone would also move
    it in the image), and the depth can never become negative.
    """
    z = control_points[..., 2:3]
    return torch.cat([control_points[..., :2] / z, torch.log(z)], dim=-1)


def rotation_from_6d(rot6d: torch.Tensor) -> torch.Tensor:
    """``(S, 6)`` the first two columns of a rotation (Zhou et al. 2019) -> ``(S, 3, 3)``, by Gram-Schmidt
    (``pytorch_kinematics.rotation_6d_to_matrix``, which takes rows, on the transpose)."""
    return pk.rotation_6d_to_matrix(rot6d).transpose(-1, -2)


def rotation_to_6d(R: torch.Tensor) -> torch.Tensor:
    """``(S, 3, 3)`` rotations -> ``(S, 6)`` their first two columns (the inverse of ``rotation_from_6d``)."""
    return pk.matrix_to_rotation_6d(R.transpose(-1, -2))


def state_to_control_points(state: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`control_points_to_state`: ``(S, n+1, 3)`` camera-frame control points, metres."""
    z = torch.exp(state[..., 2:3])
    return torch.cat([state[..., :2] * z, z], dim=-1)


def _apparent_radius(coverage: np.ndarray, mask: np.ndarray, path: np.ndarray, step_px: float = 0.5) -> np.ndarray:
    """Half the mask's width across the path at each path point ``(P,)`` pixels, to a fraction of a pixel.

    The width is the coverage integrated along the normal of the path (its direction over +-3 px), out to
    twice the distance to the background plus 2 px on each side (bilinear samples every ``step_px``); where the arm
    bends sharply or touches itself this over-counts, which the callers' robust fits tolerate.
    """
    inside = exact_distance_transform(mask)
    rows = np.clip(np.round(path[:, 1]).astype(np.int64), 0, mask.shape[0] - 1)
    cols = np.clip(np.round(path[:, 0]).astype(np.int64), 0, mask.shape[1] - 1)
    reach = 2.0 * inside[rows, cols] + 2.0  # (P,)
    cum = polyline_arc_length(path)
    ahead = np.stack([np.interp(np.minimum(cum + 3.0, cum[-1]), cum, path[:, d]) for d in range(2)], axis=1)
    behind = np.stack([np.interp(np.maximum(cum - 3.0, 0.0), cum, path[:, d]) for d in range(2)], axis=1)
    tangent = ahead - behind
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # (P, 2)
    t = np.arange(-float(reach.max()), float(reach.max()) + step_px / 2, step_px)  # (T,)
    samples = path[:, None, :] + t[None, :, None] * normal[:, None, :]  # (P, T, 2)
    values = cv2.remap(coverage, samples[..., 0].astype(np.float32), samples[..., 1].astype(np.float32),
                       cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)  # (P, T)
    values = values * (np.abs(t)[None, :] <= reach[:, None])
    return np.maximum(0.5 * step_px * values.sum(axis=1), 0.5)


def _fit_bezier(points: np.ndarray, parameters: np.ndarray, order: int, rounds: int = 4) -> np.ndarray:
    """Least-squares Bezier control points ``(order+1, D)`` through ``points`` ``(P, D)``, starting from the given
    curve parameters ``(P,)`` and re-parametrising each point to its nearest curve point between rounds (the
    ends stay at 0 and 1)."""
    t = parameters.copy()
    dense = np.linspace(0.0, 1.0, 256)
    dense_basis = bernstein_basis(order, torch.from_numpy(dense)).numpy()  # (256, n+1)
    for round_ in range(rounds + 1):
        basis = bernstein_basis(order, torch.from_numpy(t)).numpy()  # (P, n+1)
        control = np.linalg.lstsq(basis, points, rcond=None)[0]
        if round_ == rounds:
            break
        curve = dense_basis @ control  # (256, D)
        nearest = np.argmin(((points[:, None] - curve[None]) ** 2).sum(-1), axis=1)  # (P,)
        t = np.maximum.accumulate(dense[nearest])  # keep the order along the path
        t[0], t[-1] = 0.0, 1.0
    return control


def _cap_edge(end: torch.Tensor, previous: torch.Tensor, ring: torch.Tensor) -> torch.Tensor:
    """Outer edge of an end cap in the image: ``end`` (S, 2) moved along the unit direction ``end - previous``
    to the farthest vertex of ``ring`` (S, A, 2) in that direction (not moved when none lies beyond)."""
    direction = end - previous
    direction = direction * torch.rsqrt((direction * direction).sum(-1, keepdim=True) + 1e-12)  # (S, 2)
    reach = ((ring - end[:, None]) * direction[:, None]).sum(-1).amax(dim=1).clamp(min=0.0)  # (S,)
    return end + reach[:, None] * direction


def arc_length_fractions(points: torch.Tensor) -> torch.Tensor:
    """Fraction of the polyline's length at each vertex: ``(S, R, 3)`` -> ``(S, R)`` from 0 to 1 (differentiable)."""
    step = points[:, 1:] - points[:, :-1]  # (S, R-1, 3)
    length = torch.sqrt((step * step).sum(-1) + 1e-18)  # (S, R-1)
    cum = torch.cat([length.new_zeros(length.shape[0], 1), torch.cumsum(length, dim=1)], dim=1)  # (S, R)
    return cum / cum[:, -1:]


def radius_profile_at(profile: torch.Tensor, fractions: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of radius profiles ``(S, n)`` given at arc-length fractions ``j / (n - 1)`` to the
    fractions ``(S, R)`` in [0, 1]: returns ``(S, R)`` (differentiable in both)."""
    n = profile.shape[1]
    x = fractions.clamp(0.0, 1.0) * (n - 1)  # (S, R) in profile-sample units
    lower = x.detach().floor().long().clamp(0, n - 2)
    t = x - lower.to(x.dtype)
    return profile.gather(1, lower) * (1.0 - t) + profile.gather(1, lower + 1) * t


def consistent_taper_fractions(
    rays: np.ndarray,
    cum: np.ndarray,
    middle: np.ndarray,
    weight: np.ndarray,
    depths: Callable[[np.ndarray], np.ndarray],
    rounds: int = CONSISTENT_TAPER_ROUNDS,
) -> np.ndarray:
    """Each skeleton path point's fraction of the arm's 3D arc length, solved together with its width depth.

    A part of the arm that runs towards or away from the camera is foreshortened in the image, so the path
    fraction is not where along the arm a path point lies, and the taper's radius taken there (hence the depth from
    the apparent width) is off. Each round takes the depths at the current fractions, smooths them (a Gaussian of
    5 % of the path; outside ``middle``, at the caps, their weighted line), back-projects the path at them and takes
    the 3D arc-length fractions of those points.

    Args:
        rays: ``(P, 3)`` the path points' rays (``z = 1``).
        cum: ``(P,)`` arc length along the path in the image (pixels), from 0.
        middle: ``(P,)`` bool, the points whose width is trusted.
        weight: ``(M,)`` the weights of the ``M`` points in ``middle`` in the line's least squares.
        depths: fractions ``(P,)`` -> depths ``(P,)`` (metres) from the apparent width with the taper there.
        rounds: how many times; 0 returns the path fractions.

    Returns:
        ``(P,)`` fractions from 0 to 1, non-decreasing.
    """
    frac = cum / cum[-1]
    for _ in range(rounds):
        depth = depths(frac)
        a, b = _depth_line(frac, depth, middle, weight)
        z = _smooth_along(np.where(middle, depth, a + b * (frac - 0.5)), cum, 0.1 * cum[-1])
        arc = polyline_arc_length(rays * np.maximum(z, 1e-3 * float(np.median(z[middle])))[:, None])
        frac = arc / max(float(arc[-1]), 1e-12)
    return frac


def _depth_line(fractions: np.ndarray, depth: np.ndarray, middle: np.ndarray, weight: np.ndarray
                ) -> tuple[float, float]:
    """``(a, b)`` of the depth line ``a + b (s - 1/2)`` over path fractions ``s``: weighted least squares of the
    depths ``(P,)`` at the ``middle`` points ``(P,)`` bool, with their ``weight`` ``(M,)``."""
    design = np.stack([np.ones(int(middle.sum())), fractions[middle] - 0.5], axis=1)  # (M, 2)
    a, b = np.linalg.lstsq(design * weight[:, None], depth[middle] * weight, rcond=None)[0]
    return float(a), float(b)


def _smooth_along(values: np.ndarray, cum: np.ndarray, width: float) -> np.ndarray:
    """``values`` ``(P,)`` along a path smoothed by a Gaussian of standard deviation ``width / 2`` in arc length
    ``cum`` ``(P,)`` (a weighted mean of every point, so the ends are not pulled towards zero)."""
    sigma = max(0.5 * width, 1e-9)
    w = np.exp(-0.5 * ((cum[:, None] - cum[None, :]) / sigma) ** 2)  # (P, P)
    return (w @ values) / w.sum(axis=1)
