"""Camera-to-robot pose of a rigid manipulator from one mask and its joint readings (DESIGN.md 1.2).

    T_cam_root* = argmin  w_mask L_mask + w_dist L_dist + w_app L_app  (+ w_offset L_offset)

over the pose ``T_cam_root`` and (optionally) per-vertex offsets of the link geometry, by
:func:`pipeline.optimize.fit` (Adam, many starts in one batch, the best parameters seen kept). The method in full,
with the reasons for each choice: ``docs/method.md`` ("Rigid manipulators: camera-to-base pose"); measured
accuracy and speed: ``docs/accuracy.md``; what was tried and not adopted: ``docs/decisions.md``.

Convention:
    Camera frame OpenCV (x right, y down, z forward), metres, radians; ``p_cam = T_cam_root @ p_root``; pixels
    ``(u, v)`` = (column, row), pixel centres at integers; ``image_size`` is ``(H, W)``.

Sections of ``docs/method.md`` the code below refers to:

- Parametrisation: per start, ``pose (S, 6) = (w, a, b, log z)``: an axis-angle ``w`` about a reference rotation
  re-based at every stage, and the mesh's bounding-box centre at ``t = z (a, b, 1)``; ``offsets (S, V, 3)`` metres
  in the link frames (``lr_offsets``, 0 by default), only in stages that render the link meshes.
- Losses: ``L_mask``, ``L_dist``, ``L_app`` each divided by the mask's area at the stage's working resolution
  (:mod:`pipeline.losses`), so that the default weights hold at any resolution.
- Straight-through silhouette: the losses take the hard silhouette's value and the soft one's gradient,
  ``S = S_soft + (S_hard - S_soft).detach()``.
- Initialisation and stages: random rotations placed on the mask by moment matching, ranked by IoU; coarse stages
  on the link hulls, the last on the link meshes; mask components no start explains are dropped between stages.
  Optionally the starts that go on are the best one per basin (``keep_separation_deg``) and, before the first
  mesh stage, ranked by the meshes' loss at the poses the hulls reached (``rank_by_meshes``); both off by default
  (measured: no gain on real robots' noisy masks, docs/any-manipulator.md).
- Robust mask term (``fit_boundary_offset``): a segmenter that draws the robot's outline ``delta`` pixels too wide
  (or too narrow) biases the depth, since a nearer robot draws a larger outline (2 px cost 4-7 cm on real arms at
  640x480, ``docs/any-manipulator.md``). Before each mesh stage after the first, ``delta`` is estimated from link
  widths: the mask's inner distance against the best start's silhouette's along that silhouette's skeleton, as the
  intercept of a line (a dilation adds ``delta`` to every width, a depth error scales them; ``_boundary_offset``);
  the stage then fits the mask's level set ``delta`` inside its edge. The polish estimates it once more, from the
  link meshes' pose of the last stage (the earlier estimates come from poses fitted with the link hulls, which are
  wider than the links). With ``polish_boundary_offset`` (the default with CAD meshes) the polish then fits
  ``delta`` beside the pose, from that estimate: the links' lengths, which a dilation barely changes and the
  depth scales, then separate the two as well as the widths.
- Hidden parts (``weight_hidden``, 1 by default, 0.25 for masks with holes): where the rendered robot lies more
  than ``hidden_margin_px`` outside the mask, its pixels count ``weight_hidden`` instead of 1, in the mask term and
  in ``L_dist``: a box in front of the arm or a segmenter that misses a link leaves a hole that the right pose must
  draw over, and at full weight a wrong pose that tucks the arm into the visible part often costs less
  (docs/any-manipulator.md). The mask's own pixels keep their full weight, as do those near its outline.
- Retries: a fit whose loss stays above ``retry_loss`` runs again with the next seed; the lower loss is kept. Where
  the model carries its visual meshes beside link hulls (``ManipulatorModel.outline``; not beside CAD meshes, where
  the outline is the same meshes finer), the question is asked of them instead: the meshes' loss at the fit's pose
  against ``retry_outline_loss`` (a hull is wider than its link, so a clean mask's right pose can leave the hulls' own
  loss above ``retry_loss``). The
  retry gives up after stage ``retry_compare_stage`` unless its best loss there is at least ``retry_min_gain``
  below the first fit's at the same stage (it found the same basin, or an equally poor one: on real robots'
  collision geometry the loss stays above ``retry_loss`` in the right basin too, docs/any-manipulator.md). By
  default the retry fits with the hidden weight ``retry_weight_hidden`` (0.25) instead: a mask that the first
  fit leaves poorly explained often has a hole (an occluder, a segmenter's miss), and a pose that draws the robot
  over it then costs less. It runs in full (its stage losses are not comparable with the first fit's), and the
  two poses are compared under the retry's loss (``_better``), so the first fit is kept where drawing over the
  mask's holes does not explain the mask better. The attempt not kept stays in the result
  (``PoseResult.other_attempts_T_cam_root``, with its loss over the kept one's under that comparison), and
  :func:`pose_ambiguity` counts it as a runner-up like the fit's own starts.
- Boundary refits (``boundary_refits``): the stages fit the mask as it is, so a segmenter's outline drawn 2 px too
  wide (or narrow) pulls them, before any offset is fitted, to a pose nearer (farther) or turned; the polish then
  finds most of the offset but cannot leave that basin (on Baxter's tuning views at 640x480 the true pose scored
  half the answer's loss at the right offset). A fit whose polish fits the offset (``polish_boundary_offset``: CAD
  meshes by default) and found it at least ``boundary_refit_px`` runs again on the mask's level set at that
  offset (the bias taken off before the stages), under the hidden weight of the fit kept and without retries, and
  the lower loss is kept; the other fit's pose stays among the result's other attempts, a runner-up for
  :func:`pose_ambiguity` (docs/any-manipulator.md). The offset asked is the one the fit's own geometry's polish
  found, before a CAD fit's polish drawn within 1 mm (``outline_polish``): that finer outline fits a noisy mask's
  edge errors more closely, reports larger offsets and set off refits that mostly ended farther.
- Polish: Levenberg-Marquardt steps, then a random search, on the hard-silhouette loss of the best start
  (:func:`_polish`); a step is taken only when it lowers the loss.
- Rendering: back faces are culled on closed, consistently wound meshes, and on others where the pose the mesh
  stages start from shows no back face through a hole (``PoseFitConfig.cull_open_tolerance``); while a fit runs
  torch is set to one thread (``pipeline.render.single_torch_thread``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from kornia.geometry.conversions import Rt_to_matrix4x4, quaternion_to_rotation_matrix
from skimage.morphology import skeletonize

from pipeline.camera import Camera, check_image_matches_camera, resize_camera, undistort_image, working_size
from pipeline.checks import check_positive, check_shape
from pipeline.errors import ConfigError, PipelineError, ShapeError
from pipeline.geometry import rotvec_to_rotmat
from pipeline.losses import appearance_loss, distance_loss, mask_loss
from pipeline.optimize import AdamMoments, ParamGroup, fit
from pipeline.preprocess import check_mask, distance_to_mask, exact_distance_transform, foreground_window
from pipeline.render import SoftRasterSettings, render_hard, render_silhouette_packed, single_torch_thread
from pipeline.robots.manipulator import ManipulatorModel
from pipeline.viz import draw_frames, draw_outline

__all__ = ["PoseStage", "PoseFitConfig", "PoseResult", "PoseAmbiguity", "estimate_pose", "estimate_pose_from_readings",
           "StaticCameraConfig", "StaticCameraResult", "refine_static_camera", "frames_in_camera", "pose_ambiguity",
           "pose_loss_at", "render_pose_mask", "draw_pose_overlay", "pose_result_json", "stage_best_losses"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class PoseStage:
    """One stage of the coarse-to-fine schedule.

    Fields:
        fraction: share of ``PoseFitConfig.iterations`` run in this stage (the shares must sum to 1).
        scale: working resolution of this stage relative to the config's working resolution, in (0, 1].
        keep: starts that enter this stage (the best of the previous stage; the first stage takes all).
        sigma_px2: softness of the silhouette, squared pixels of this stage's resolution.
        lr_scale: multiplies both learning rates in this stage.
        final_lr_factor: the rates decay geometrically to ``lr * lr_scale * final_lr_factor`` at the stage's
            last step (``pipeline.optimize.fit``); 1 keeps them constant.
        straight_through: evaluate the losses on the hard silhouette and take their gradient through the soft
            one (see the module docstring); ``False``: the soft silhouette for both, as in the paper.
        hull: render each link's convex hull instead of its mesh, without vertex offsets (cheap coarse stages).
    """

    fraction: float
    scale: float
    keep: int
    sigma_px2: float
    lr_scale: float = 1.0
    final_lr_factor: float = 1.0
    straight_through: bool = True
    hull: bool = False

    def __post_init__(self) -> None:
        if not (0.0 < self.fraction <= 1.0):
            raise ConfigError(f"PoseStage.fraction: expected a number in (0, 1], got {self.fraction!r}")
        if not (0.0 < self.scale <= 1.0):
            raise ConfigError(f"PoseStage.scale: expected a number in (0, 1], got {self.scale!r}")
        if isinstance(self.keep, bool) or not isinstance(self.keep, int) or self.keep < 1:
            raise ConfigError(f"PoseStage.keep: expected an int >= 1, got {self.keep!r}")
        check_positive(self.sigma_px2, "PoseStage.sigma_px2")
        check_positive(self.lr_scale, "PoseStage.lr_scale")
        check_positive(self.final_lr_factor, "PoseStage.final_lr_factor")


#: ``(iterations, polish_rounds, polish_newton_patience, polish_min_step_px, polish_boundary_offset)`` of a fit
#: whose ``PoseFitConfig`` leaves them ``None``: CAD meshes get the long schedule (its last millimetres are what the
#: 10 mm target needs), with the polish's early stops (0.85x the fit's time on tuning views, same PCK rates) and
#: the boundary offset fitted in the polish (a segmenter's dilation or erosion; CAD draws the robot's outline, so
#: the offset is the mask's), every other geometry (primitives, hulls) the short one, which keeps the PCK rates on
#: real robots at 0.6x the time, its polish in full and no offset (a hull's outline is wider than the robot's: the
#: offset would take that for the mask's; docs/any-manipulator.md).
SCHEDULE_BY_GEOMETRY = {"cad": (500, 40, 3, 0.1, True, 7.0), "other": (300, 10, 0, 0.0, False, 20.0)}

#: ``(polish_newton_steps, polish_rounds)`` of the outline polish of a CAD fit, whose model's ``outline`` is its own
#: meshes within 1 mm of their outline (``pipeline.robots.manipulator.CAD_OUTLINE_TOLERANCE_M``): it starts from
#: the answer of the fit's own polish, so a few Levenberg-Marquardt steps (each 19 renders of the finer meshes) take
#: it most of the way at a second or so; the full polish of a CAD fit (15 steps and 40 rounds) took 2-3 s more, over
#: the issue's 10 s on Baxter (docs/any-manipulator.md).
CAD_OUTLINE_POLISH = (6, 0)

DEFAULT_STAGES = (
    PoseStage(fraction=0.2, scale=0.125, keep=32, sigma_px2=0.5, hull=True),
    PoseStage(fraction=0.3, scale=0.25, keep=8, sigma_px2=0.5, hull=True),
    PoseStage(fraction=0.2, scale=0.5, keep=2, sigma_px2=0.5, hull=True),
    PoseStage(fraction=0.3, scale=1.0, keep=1, sigma_px2=0.5, lr_scale=0.3, final_lr_factor=0.1),
)


@dataclass(frozen=True, kw_only=True)
class PoseFitConfig:
    """Settings of :func:`estimate_pose` (see the module docstring for the losses and the parametrisation).

    Fields:
        iterations: Adam steps in all, shared by the stages by their ``fraction``; ``None`` (the default) meaning
            *by the link geometry* (:meth:`for_geometry`): 500 for CAD meshes, 300 for every other geometry.
        starts: hypotheses optimised together in the first stage (fewer if the candidates run out, see
            ``min_start_separation_deg``).
        candidates: random rotations scored to pick the ``starts`` (>= ``starts``).
        init_max_side: longest side (pixels) of the image that scoring renders (at most the working resolution).
        min_start_separation_deg: the starts are the best-scoring candidates at least this far apart in rotation
            (fewer if the candidates run out).
        keep_separation_deg: between stages, the starts that go on are the lowest-loss ones at least this far
            apart in rotation (one per basin; the stage is filled with the next lowest when fewer basins are
            found); 0 (the default): simply the lowest-loss ones (several of which may sit in one basin). With
            ``rank_by_meshes`` and a third stage keeping 3 it fixed a turned pose on a tuning view but gained
            nothing on the reported noisy views (docs/any-manipulator.md), hence off.
        rank_by_meshes: before the first stage that renders the link meshes, rank the starts still alive by that
            stage's loss (its resolution and softness, on the mask itself, not a boundary offset's level set) at
            the poses the hull stages reached (one render each) instead of by the hull loss: the
            hulls are wider than the links and may prefer a turned pose that the meshes' outline rules out. Off
            by default (see ``keep_separation_deg``).
        flip_candidates: also score, for each of this many best candidates, its three 180-degree turns about the
            mask's principal axes in the image plane and about the optical axis (the mirror images a
            near-symmetric silhouette allows, e.g. a stretched arm seen from the side); 0 = off (the default until
            the cross-robot benchmark decides, ``docs/accuracy.md``).
        seed: seed of the random initial rotations.
        working_max_side: longest side of the working resolution (pixels); larger images are shrunk to it.
        stages: the coarse-to-fine schedule; each stage's ``keep`` is capped by ``starts``.
        lr_pose: Adam learning rate of ``(w, a, b, log z)`` (rad, normalised image units, log metres).
        lr_offsets: Adam learning rate of the vertex offsets (metres; the paper's 1e-4); 0, the default, freezes
            them: offsets trade depth for shape (a mesh grown by an offset looks like one moved closer), and on
            our synthetic cases they made the end effector's 3D error worse (docs/decisions.md).
        weight_mask, weight_distance, weight_appearance: loss weights (paper 1, 1, 1; here 1, 1, 0). The
            appearance term (the silhouette's area against the mask's) is off by default: it is an exact depth cue
            only when the link geometry draws exactly the mask's outline; with collision primitives, decimated
            meshes or a segmenter's mask it pulls the depth towards a wrong area (on Panda, UR5 and Baxter, clean
            masks from another renderer, median depth error of the end effector with it / without it: collision
            geometry 57 / 2.6, 130 / 6.3, 343 / 156 mm; CAD 3.6 / 1.9, 7.1 / 2.0, 7.4 / 4.7 mm;
            docs/any-manipulator.md).
        gamma: distance scale of ``L_dist`` (paper 100), in reference pixels.
        reference_side: longest image side at which distances are measured (pixels).
        weight_offset: weight of the offset regulariser ``L_offset``.
        offset_scale_m: offset size (metres) at which ``L_offset`` reaches 1 per vertex.
        drop_unexplained: before every stage after the first, drop the mask's connected components that the best
            start's silhouette does not come within ``unexplained_margin_px`` of (false positives: they would
            bias the appearance term); never more than half of the mask's area.
        unexplained_margin_px: that distance, in reference pixels (see ``reference_side``).
        fit_boundary_offset: before every stage that renders the link meshes (not the first) and before the
            polish, estimate how far the mask's edge lies outside the best start's silhouette (``delta``: a
            segmenter's dilation, > 0, or erosion, < 0) from link widths along the silhouette's skeleton, and fit
            the mask's level set ``delta`` inside its edge instead of the mask (module docstring, Robust mask term).
        boundary_offset_min_px, boundary_offset_max_px: ``delta`` is taken as 0 below the first (what the estimate
            cannot tell from its own noise) and above the second (more than a segmenter's bias: the pose is then
            more likely wrong), reference pixels.
        boundary_search_px: each inner distance compared is the largest within this radius (reference pixels).
        cutoff_eps: outside probability at which a face stops counting (sets the render cut-off).
        saturation: in the stages that draw the link meshes (not ``PoseStage.hull``), a pixel whose soft
            silhouette ``S`` has ``1 - S`` below ``e^-saturation`` counts as covered: the rasterizer skips its
            remaining faces and it passes no gradient (``SoftRasterSettings.saturation``, whose default of 20 the
            hull stages keep). ``None``: by the link geometry (``SCHEDULE_BY_GEOMETRY``): 7 (``1 - S < 1e-3``) for
            CAD meshes, whose pixels lie near the edges of every small face over them and saturate only after many
            of them, 20 for the others (docs/any-manipulator.md).
        hull_points: the coarse stages' link hulls (``PoseStage.hull``) and the starts' scoring keep at most this
            many vertices per link (farthest-point sampling of the hull's vertices, at most ``2 n - 4`` faces,
            grown to the full hull's volume: ``_link_hulls``). Those stages only choose the basin, at 80-320 px,
            where a link spans a few dozen pixels, and their cost is mostly per face (32 starts in the first).
            Not the link geometry of a fit without CAD (its last stage and polish draw the model's own faces,
            hulls of up to ``load_robot``'s ``hull_faces``). 16 makes a fit 0.64-0.77x as long without CAD and
            0.74-0.96x with CAD on Panda, UR5 and Baxter, at about the same rates, but turned 4 of 180 reported
            fits by more than 20 degrees against 2 with 48, hence 48 (docs/any-manipulator.md).
        cull_back_faces: skip faces turned away from the camera where that leaves the silhouette as it is: on a
            closed, consistently wound mesh (checked once per model), and on any other (most CAD meshes: several
            parts, decimated) from the first mesh stage on when, at the best start's pose there, culling takes at
            most ``cull_open_tolerance`` of the mesh's hard silhouette away (no hole shows a back face; checked
            once per fit, ``_cull_if_unseen``). Otherwise all faces are drawn.
        cull_open_tolerance: that share (0: never cull a mesh that is not closed).
        retries: fits run again, each with the next ``seed``, while the best loss stays above ``retry_loss``; the
            lowest loss is kept (``PoseResult.attempts`` counts the fits).
        retry_loss: the loss above which a fit counts as stuck in a wrong basin (module docstring, Retries).
        retry_outline_loss: for a model with an ``outline`` (its visual meshes kept beside link hulls: ``load_robot``
            does so by default where links are drawn as hulls; not a CAD model's own meshes, finer), the retry runs
            when the outline's loss at the fit's pose (the last stage's loss, against the mask the fit kept) is above
            this instead of when the fit's own
            loss is above ``retry_loss``: a hull is wider than its link, and on real robots' clean masks a first fit
            in the right basin ended above ``retry_loss`` on 9 of 10 UR5 tuning views (0.148-0.220), each then
            retried for about 4 s, while its outline's loss was 0.019-0.054 there (clean tuning views of Panda,
            UR5 and Baxter: 0.006-0.054 and 0.101 for a fit 18 degrees off; noisy ones 0.130-0.616). ``None``: by
            the fit's own loss always (docs/any-manipulator.md).
        outline_polish: for a model with an ``outline``, polish the answer once more drawn with the visual meshes,
            after the fit and its retries: the polish of a CAD fit (``SCHEDULE_BY_GEOMETRY["cad"]``'s early stops,
            40 random-search rounds, none where ``polish_rounds`` is 0, as in the tracker's warm fits; the boundary
            offset fitted), from the answer's pose, against the mask the fit kept. ``T_cam_root``,
            ``boundary_offset_px`` and ``depth_std_m`` are then the outline's, ``loss`` stays the fit's (its own
            geometry's; ``outline_loss`` is the outline's). ``True``: always; ``False``: never;
            ``None`` (the default): when a retry ran (the mask was left poorly explained: often a segmenter's
            outline too wide or too narrow, or a hole, where the hulls' overdraw and the mask's bias confound the
            depth), and always on a CAD model whose ``outline`` is its own meshes within 1 mm (``load_robot``
            builds it where the face budget leaves a link farther off) in a fit that may retry (not the tracker's warm
            frames), with the short schedule ``CAD_OUTLINE_POLISH``. On the project's reported views of Panda, UR5 and
            Baxter at 640x480 the default took noisy
            masks' end effectors within 50 mm from 0.30 / 0.50 / 0.10 to 0.80 / 0.75 / 0.35 for 1.0-2.9 s more, and
            clean fits (which rarely retry) stayed under 7 s; ``True`` took clean masks' from within 5 px and 10 mm
            on 0.85 / 0.60 / 0.60 to 1.00 / 0.85 / 0.95 for 0.5-2.6 s more (docs/any-manipulator.md). On the
            shipped network's masks of 60 rendered views the default's polish was nearer on 17 of 32 retried fits,
            farther on 15 (docs/any-manipulator.md, "A learned segmenter's masks").
        outline_polish_loss: with ``outline_polish`` ``None``, also polish with the outline where no retry ran when
            the outline's loss at the fit's answer (``retry_outline_loss``'s question) is above this: for fits that
            run no retries, the tracker's warm frames (``pipeline.track.WARM_POSE_FIT``). ``None`` (the default):
            only after a retry.
        offset_polish_loss: with the link geometry's own polish not fitting the boundary offset
            (``polish_boundary_offset`` off: hulls), a fit from a given start (``initial_T_cam_root``: the tracker's
            warm frames) fits it in its polish all the same when the outline's loss (``retry_outline_loss``'s
            question) at the answer before the polish is above this: a mask the links leave poorly explained,
            often one drawn too wide or too narrow, where the hulls' overdraw and the mask's bias confound the depth.
            ``None`` (the default): never. ``track pose --warm-boundary-offset auto`` sets 0.08 on the warm frames
            (docs/tracking.md, "The warm frames' boundary offset in the hulls' polish").
        retry_compare_stage: the stage (1-based) after which a retry compares its best loss with the kept fit's at
            the same stage and gives up unless it is lower by ``retry_min_gain`` (a fraction); 0: every retry
            runs in full.
        boundary_refits: a fit whose polish fits the boundary offset (``polish_boundary_offset``: CAD meshes by default)
            and found it at least ``boundary_refit_px`` from 0 (that polish's offset, before the outline polish of a CAD
            fit; ``PoseResult.boundary_offset_px`` is the answer's) runs again on the mask's level set at that offset,
            i.e. with the segmenter's bias taken off before the stages (module docstring, Boundary refits), as the fit
            it kept ran (its hidden weight, the outline polish where it had one) but without retries; further refits go
            on from the offsets found added up while the last fit still finds one that far, never beyond
            ``boundary_offset_max_px`` in all (that far off, a wrong basin is likelier than such a mask). At most this
            many refits (1 by default: a second one made 2 of 62 measured fits worse and none better; 0: never); the
            lowest loss is kept, each fit's against its own level set of the mask (``_better``). A clean mask's offset
            is about 0, so its fit runs once. Not for a hull fit's outline polish by default (measured no better:
            docs/any-manipulator.md).
        boundary_refit_px: that offset, reference pixels (> 0).
        polish_newton_steps: Gauss-Newton steps of the polish of the best pose on the last stage's loss (module
            docstring, Polish); 0 for none.
        polish_rounds: random-search rounds of the polish after them; 0 for none (no polish when both are 0);
            ``None`` (the default) meaning *by the link geometry*: 40 for CAD meshes, 10 for every other geometry.
            (Measured on Panda, UR5 and Baxter, 20 clean views each at 640x480: with hulls, 300 / 10 keeps the
            PCK rates of 500 / 40 (within one view) at 0.6x the time, 5-7 s a fit; with CAD it costs millimetres
            that the 10 mm target needs; docs/any-manipulator.md.)
        polish_samples: random pose perturbations tried per polish round.
        polish_newton_patience: the Levenberg-Marquardt steps end after this many in a row found no lower loss
            (each failure raises the damping tenfold, so later steps only shrink); 0: all ``polish_newton_steps``;
            ``None`` (the default): by the link geometry, 3 for CAD meshes, 0 for every other geometry.
        polish_min_step_px: the random search ends once its step has shrunk below this (pixels of the last
            stage); 0: all ``polish_rounds``; ``None`` (the default): by the link geometry, 0.1 for CAD meshes, 0
            for every other geometry. (Both measured with CAD on Panda, UR5 and Baxter tuning views: the same PCK
            rates at 0.85x the fit's time, medians a few tenths of a millimetre higher; docs/any-manipulator.md.)
        polish_step_px: the polish's step: the image motion (pixels of the last stage) of a finite-difference
            probe and the initial standard deviation of the random perturbations.
        polish_boundary_offset: the polish fits the boundary offset ``delta`` (as ``fit_boundary_offset`` defines
            it) as a seventh unknown beside the pose, from the widths' estimate (:func:`_polish`): beside the pose,
            the links' lengths as well as their widths tell it from the depth. ``None`` (the default): by the link
            geometry, on for CAD meshes (whose outline is the robot's), off for every other geometry (a hull or a
            primitive is not the robot's outline, and the offset would take the difference for the mask's). On
            real robots' noisy masks (a 2 px dilation or erosion among other errors), tuning views: end effector
            within 50 mm on 8 of 15 fits against 2 of 15; clean masks unchanged (docs/any-manipulator.md).
        weight_hidden: weight of the mask term (and of ``L_dist``) at pixels more than ``hidden_margin_px``
            outside the mask (module docstring, Hidden parts): the robot may be there, hidden by an occluder or
            missed by the segmenter, so a pose that draws it there pays less than one that leaves the mask's
            pixels unexplained. 1 (the default): every pixel alike. **0.25 is the setting for masks with holes**
            (an occluder, a segmenter's misses): on real robots' noisy masks, reported views at 640x480 with CAD,
            end effector within 20 px 0.90 / 0.90 / 0.55 -> 1.00 / 0.90 / 0.90 (Panda, UR5, Baxter), within
            50 mm 0.60 / 0.65 / 0.20 -> 0.75 / 0.75 / 0.35; but on clean masks 5 of 60 fits fall out of 5 px and
            10 mm (two of them wrong basins: the link hulls of the coarse stages stick out of a clean mask by more
            than the margin), hence not the default of the first fit; the retry's (``retry_weight_hidden``) instead.
        retry_weight_hidden: the ``weight_hidden`` of the retries (``None``: ``weight_hidden``'s). When it differs
            (the default: 0.25 against 1), a fit that leaves the mask poorly explained (loss above ``retry_loss``)
            is tried again (next seed) on the hypothesis that parts of the robot are hidden, without giving up at
            ``retry_compare_stage`` while the kept fit's stage losses are another loss's, and a retry's fit
            replaces the kept one only if its pose scores lower under the retry's weight (module docstring,
            Retries). A clean mask's fit, which ends below ``retry_loss``, keeps the full weight. On real robots'
            noisy masks (tuning views) it keeps most of ``weight_hidden`` 0.25's gain at about 1.35x the time of
            a noisy fit; clean masks' fits are unchanged (docs/any-manipulator.md).
        hidden_margin_px: that margin, reference pixels: beyond a segmenter's outline errors (1-2 px) and a
            slightly wrong pose's, so that the outline's fit keeps its full weight.
        coverage_target: the mask term compares the silhouette with the share of each working pixel that the mask
            covers (0-1, area-averaged) instead of the downsampled mask thresholded at half cover (the distance
            term and the weights keep the thresholded mask); no change where the working resolution is the
            mask's. Off for single-image fits (validated on the cross-robot benchmark with it off); on in the
            tracker's warm fits (``pipeline.track.WARM_POSE_FIT``) and the static-camera refinement, whose working
            sides (480 and 320 px) shrink a frame: on tuning videos the tracked end effector's 3D error went down
            on 7 of 14 and up on 5 (mostly UR5's and Baxter's noisy masks), the static camera's down on 9 and up
            on 3 (``docs/tracking.md``). ``_PolishWindow.loss`` compares the same target; with CAD's fitted
            boundary offset the polish's level sets stay 0/1.
        record_trajectory: keep every start's pose at every iteration (``PoseResult.trajectory``; 128 bytes per
            start and iteration).
    """

    iterations: int | None = None
    starts: int = 32
    candidates: int = 512
    init_max_side: int = 80
    min_start_separation_deg: float = 30.0
    keep_separation_deg: float = 0.0
    rank_by_meshes: bool = False
    flip_candidates: int = 0
    seed: int = 0
    working_max_side: int = 640
    stages: tuple[PoseStage, ...] = DEFAULT_STAGES
    lr_pose: float = 1e-2
    lr_offsets: float = 0.0
    weight_mask: float = 1.0
    weight_distance: float = 1.0
    weight_appearance: float = 0.0
    gamma: float = 100.0
    reference_side: int = 640
    weight_offset: float = 1e-3
    offset_scale_m: float = 0.01
    drop_unexplained: bool = True
    unexplained_margin_px: float = 12.0
    fit_boundary_offset: bool = False
    boundary_offset_min_px: float = 1.0
    boundary_offset_max_px: float = 4.0
    boundary_search_px: float = 4.0
    cutoff_eps: float = 1e-3
    saturation: float | None = None
    hull_points: int = 48
    cull_back_faces: bool = True
    cull_open_tolerance: float = 1e-3
    retries: int = 1
    retry_loss: float = 0.15
    retry_outline_loss: float | None = 0.08
    outline_polish: bool | None = None
    outline_polish_loss: float | None = None
    offset_polish_loss: float | None = None
    retry_compare_stage: int = 2
    retry_min_gain: float = 0.1
    boundary_refits: int = 1
    boundary_refit_px: float = 1.0
    polish_newton_steps: int = 15
    polish_rounds: int | None = None
    polish_samples: int = 16
    polish_newton_patience: int | None = None
    polish_min_step_px: float | None = None
    polish_step_px: float = 1.0
    polish_boundary_offset: bool | None = None
    weight_hidden: float = 1.0
    retry_weight_hidden: float | None = 0.25
    hidden_margin_px: float = 6.0
    coverage_target: bool = False
    record_trajectory: bool = False

    def __post_init__(self) -> None:
        for name in ("iterations", "starts", "candidates", "init_max_side", "working_max_side", "reference_side",
                     "polish_samples", "hull_points"):
            value = getattr(self, name)
            if name == "iterations" and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"PoseFitConfig.{name}: expected an int >= 1, got {value!r}"
                                  + (" (or None: by the link geometry)" if name == "iterations" else ""))
        if self.hull_points < 4:
            raise ConfigError(f"PoseFitConfig.hull_points: expected an int >= 4 (a hull needs 4 vertices), got "
                              f"{self.hull_points!r}")
        for name in ("retries", "retry_compare_stage", "polish_newton_steps", "polish_rounds", "flip_candidates",
                     "polish_newton_patience"):
            value = getattr(self, name)
            if name in ("polish_rounds", "polish_newton_patience") and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ConfigError(f"PoseFitConfig.{name}: expected an int >= 0, got {value!r}")
        check_positive(self.polish_step_px, "PoseFitConfig.polish_step_px")
        if self.polish_boundary_offset is not None and not isinstance(self.polish_boundary_offset, bool):
            raise ConfigError(f"PoseFitConfig.polish_boundary_offset: expected True, False or None (by the link "
                              f"geometry), got {self.polish_boundary_offset!r}")
        if self.polish_min_step_px is not None:
            check_positive(self.polish_min_step_px, "PoseFitConfig.polish_min_step_px", allow_zero=True)
        check_positive(self.retry_loss, "PoseFitConfig.retry_loss")
        if isinstance(self.boundary_refits, bool) or not isinstance(self.boundary_refits, int) \
                or self.boundary_refits < 0:
            raise ConfigError(f"PoseFitConfig.boundary_refits: expected an integer >= 0 (0: never), got "
                              f"{self.boundary_refits!r}")
        check_positive(self.boundary_refit_px, "PoseFitConfig.boundary_refit_px")
        if self.retry_outline_loss is not None:
            check_positive(self.retry_outline_loss, "PoseFitConfig.retry_outline_loss")
        if self.outline_polish is not None and not isinstance(self.outline_polish, bool):
            raise ConfigError(f"PoseFitConfig.outline_polish: expected True, False or None (when a retry ran), got "
                              f"{self.outline_polish!r}")
        if self.outline_polish_loss is not None:
            check_positive(self.outline_polish_loss, "PoseFitConfig.outline_polish_loss")
        if self.offset_polish_loss is not None:
            check_positive(self.offset_polish_loss, "PoseFitConfig.offset_polish_loss")
        if not 0.0 <= self.retry_min_gain < 1.0:
            raise ConfigError(f"PoseFitConfig.retry_min_gain: expected a fraction in [0, 1), "
                              f"got {self.retry_min_gain!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise ConfigError(f"PoseFitConfig.seed: expected an int, got {self.seed!r}")
        if self.candidates < self.starts:
            raise ConfigError(f"PoseFitConfig.candidates: expected >= starts ({self.starts}), got {self.candidates}")
        if not self.stages or not all(isinstance(s, PoseStage) for s in self.stages):
            raise ConfigError("PoseFitConfig.stages: expected a non-empty tuple of PoseStage")
        total = sum(s.fraction for s in self.stages)
        if abs(total - 1.0) > 1e-6:
            raise ConfigError(f"PoseFitConfig.stages: the fractions must sum to 1, got {total:g}")
        if self.iterations is not None and self.iterations < len(self.stages):
            raise ConfigError(f"PoseFitConfig.iterations: expected at least one per stage ({len(self.stages)}), "
                              f"got {self.iterations}")
        for name in ("lr_pose", "lr_offsets", "weight_mask", "weight_distance", "weight_appearance",
                     "weight_offset"):
            check_positive(getattr(self, name), f"PoseFitConfig.{name}", allow_zero=True)
        if self.lr_pose == 0:
            raise ConfigError("PoseFitConfig.lr_pose: expected a number > 0, got 0")
        check_positive(self.gamma, "PoseFitConfig.gamma")
        check_positive(self.offset_scale_m, "PoseFitConfig.offset_scale_m")
        check_positive(self.min_start_separation_deg, "PoseFitConfig.min_start_separation_deg", allow_zero=True)
        check_positive(self.keep_separation_deg, "PoseFitConfig.keep_separation_deg", allow_zero=True)
        check_positive(self.unexplained_margin_px, "PoseFitConfig.unexplained_margin_px", allow_zero=True)
        check_positive(self.boundary_offset_max_px, "PoseFitConfig.boundary_offset_max_px", allow_zero=True)
        check_positive(self.boundary_offset_min_px, "PoseFitConfig.boundary_offset_min_px", allow_zero=True)
        check_positive(self.boundary_search_px, "PoseFitConfig.boundary_search_px", allow_zero=True)
        if isinstance(self.weight_hidden, bool) or not 0.0 <= self.weight_hidden <= 1.0:
            raise ConfigError(f"PoseFitConfig.weight_hidden: expected a weight in [0, 1] (1: every pixel alike), got "
                              f"{self.weight_hidden!r}")
        if self.retry_weight_hidden is not None and (isinstance(self.retry_weight_hidden, bool)
                                                     or not 0.0 <= self.retry_weight_hidden <= 1.0):
            raise ConfigError(f"PoseFitConfig.retry_weight_hidden: expected a weight in [0, 1] or None (weight_hidden's), "
                              f"got {self.retry_weight_hidden!r}")
        check_positive(self.hidden_margin_px, "PoseFitConfig.hidden_margin_px", allow_zero=True)
        if not 0.0 < self.cutoff_eps < 0.5:
            raise ConfigError(f"PoseFitConfig.cutoff_eps: expected a probability in (0, 0.5), got {self.cutoff_eps!r}")
        if self.saturation is not None:
            check_positive(self.saturation, "PoseFitConfig.saturation")
        if isinstance(self.cull_open_tolerance, bool) or not 0.0 <= self.cull_open_tolerance < 1.0:
            raise ConfigError(f"PoseFitConfig.cull_open_tolerance: expected a share in [0, 1) (0: never), got "
                              f"{self.cull_open_tolerance!r}")

    def for_geometry(self, primitive: str) -> PoseFitConfig:
        """This config with ``iterations``, ``polish_rounds``, ``polish_newton_patience``, ``polish_min_step_px``,
        ``polish_boundary_offset`` and ``saturation`` that are ``None`` set for a model whose links are drawn as
        ``primitive`` (``ManipulatorModel.primitive``): ``SCHEDULE_BY_GEOMETRY``."""
        defaults = SCHEDULE_BY_GEOMETRY["cad" if primitive == "cad" else "other"]
        names = ("iterations", "polish_rounds", "polish_newton_patience", "polish_min_step_px",
                 "polish_boundary_offset", "saturation")
        return dataclasses.replace(self, **{name: value if getattr(self, name) is None else getattr(self, name)
                                            for name, value in zip(names, defaults)})

    def stage_iterations(self) -> list[int]:
        """Iterations of each stage: the shares of ``iterations``, rounded, each at least 1, summing to it
        (``iterations`` set: see :meth:`for_geometry`)."""
        if self.iterations is None:
            raise ConfigError("PoseFitConfig.iterations is None (by the link geometry): resolve it with "
                              "for_geometry(model.primitive) first")
        counts = [max(1, int(round(s.fraction * self.iterations))) for s in self.stages]
        counts[-1] = max(1, self.iterations - sum(counts[:-1]))
        while sum(counts) > self.iterations:  # tiny totals: take from the largest stage
            counts[int(np.argmax(counts))] -= 1
        return counts


@dataclass(frozen=True, kw_only=True, eq=False)
class PoseResult:
    """Outcome of :func:`estimate_pose`. numpy float64 arrays, picklable.

    Fields:
        T_cam_root: ``(4, 4)`` the root link's pose in the (undistorted) camera frame, metres.
        loss: best loss of the best start (last stage, at the working resolution).
        history: ``(N, S)`` loss of every start at every iteration, stages one after another; NaN where a start
            no longer ran.
        starts_final_loss: ``(S,)`` each start's best parameters evaluated with the last stage's loss.
        T_cam_root_starts: ``(S, 4, 4)`` each start's best pose.
        best_start: index of the start returned.
        vertex_offsets: ``(V, 3)`` the best start's vertex offsets in the link frames, metres.
        joint_angles: ``(J,)`` the joint values used, rad or m (order of ``model.joint_names``).
        iterations: Adam steps in all (the stages one after another; pruned starts stop early).
        seconds: wall time of the whole estimate (preprocessing included).
        image_size: ``(H, W)`` of the input mask.
        working_size: ``(H, W)`` of the last stage.
        dropped_fraction: share of the (undistorted) mask's area dropped as unexplained (``drop_unexplained``).
        trajectory: ``(N, S, 4, 4)`` ``T_cam_root`` of every start at every iteration (where ``history`` has its
            loss; NaN elsewhere) with ``PoseFitConfig.record_trajectory``, else ``None``.
        attempts: fits run (1 + the retries used, ``PoseFitConfig.retries``); the fields above are those of the
            fit with the lowest loss, ``seconds`` counts them all.
        retries_given_up: retries stopped after ``PoseFitConfig.retry_compare_stage`` (no better basin in sight;
            counted in ``attempts``).
        loss_before_polish: the best loss of the gradient stages, before the polish (``loss`` is after it; equal
            when the polish is off or found nothing lower).
        boundary_offset_px: how far the mask's edge was found to lie outside the robot's (reference pixels):
            fitted by the polish with ``PoseFitConfig.polish_boundary_offset``, else estimated before it with
            ``fit_boundary_offset``, else 0.
        weight_hidden: the hidden weight the returned fit ran with (``PoseFitConfig.weight_hidden``, or
            ``retry_weight_hidden`` when a retry's fit was kept).
        other_attempts_T_cam_root: ``(A, 4, 4)`` the final poses of the other attempts that ran to the end (the
            first fit where a retry's was kept, or the retries that were not; after a boundary refit, also the fit
            of the other level set), ``(0, 4, 4)`` when none did.
        other_attempts_loss_ratio: ``(A,)`` their losses over the returned fit's, both under the loss that compared
            them (module docstring, Retries: the retry's hidden weight when the attempts' weights differ; a boundary
            refit's: each fit's own loss against its own level set).
        depth_std_m: the depth's standard deviation (metres, the robot's centre along the optical axis) that the
            mask leaves: from the polish's linearised mask residual at the answer (:func:`_log_depth_std`: the
            rotation, image position and boundary offset free), times ``DEPTH_STD_SCALE``; NaN without a polish.
            It says how far the silhouette pins the depth (a noisy or biased outline, a far robot, a pose seen
            along its own depth), not whether the fit found the right basin (``pose_ambiguity``).
        outline_loss: the loss of ``T_cam_root`` drawn with the model's ``outline`` (its visual meshes; the last
            stage's loss at the returned fit's hidden weight, against the mask the fit kept): asked by the retry
            (``retry_outline_loss``) and after ``outline_polish``; NaN where neither ran.
        boundary_refits: fits run again on the mask's level set (``PoseFitConfig.boundary_refits``); the fields
            above are those of the fit with the lowest loss (``loss`` against its own level set of the mask,
            ``boundary_offset_px`` from the mask given, ``attempts`` that fit's), ``seconds`` counts them all.
        moments: Adam's state of the best start after the last stage (parameter group ->
            :class:`pipeline.optimize.AdamMoments`), for a warm fit of a video's next frame to begin with
            (``estimate_pose(initial_moments=...)``). Not in the JSON.
    """

    T_cam_root: np.ndarray
    loss: float
    history: np.ndarray
    starts_final_loss: np.ndarray
    T_cam_root_starts: np.ndarray
    best_start: int
    vertex_offsets: np.ndarray
    joint_angles: np.ndarray
    iterations: int
    seconds: float
    image_size: tuple[int, int]
    working_size: tuple[int, int]
    dropped_fraction: float
    trajectory: np.ndarray | None
    attempts: int = 1
    retries_given_up: int = 0
    loss_before_polish: float = math.nan
    boundary_offset_px: float = 0.0
    weight_hidden: float = 1.0
    other_attempts_T_cam_root: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4, 4)))
    other_attempts_loss_ratio: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    depth_std_m: float = math.nan
    outline_loss: float = math.nan
    boundary_refits: int = 0
    moments: dict | None = dataclasses.field(default=None, repr=False, compare=False)


@dataclass(frozen=True, kw_only=True)
class PoseAmbiguity:
    """Whether another pose, clearly apart in rotation, explains the mask about as well as the answer.

    Fields:
        ambiguous: a pose more than ``min_angle_deg`` from the answer's rotation (another start of the returned
            fit, or the final pose of another attempt: a retry) ended within ``loss_ratio`` of the answer's loss
            (e.g. the mirrored pose of a stretched arm seen from the side).
        runner_up_start: the start of the returned fit that is the runner-up (-1 if the runner-up is another
            attempt, or no pose is that far apart).
        runner_up_attempt: the index in ``PoseResult.other_attempts_T_cam_root`` of the runner-up (-1 if it is a
            start, or none).
        runner_up_T_cam_root: ``(4, 4)`` its pose (NaN if none).
        runner_up_loss: a start's loss, evaluated with the last stage's loss; for another attempt, its loss ratio
            times the answer's start's loss (the answer's scale: the two attempts were compared under another loss
            when their hidden weights differ) (inf if none).
        runner_up_loss_ratio: its loss over the answer's under the same loss (inf if none).
        rotation_deg: its rotation away from the answer, degrees (NaN if none).
    """

    ambiguous: bool
    runner_up_start: int
    runner_up_T_cam_root: np.ndarray
    runner_up_loss: float
    rotation_deg: float
    runner_up_attempt: int = -1
    runner_up_loss_ratio: float = math.inf


#: ``pose_ambiguity``'s default ``loss_ratio``: on the cross-robot benchmark's tuning views (CAD, 640x480) every
#: start or attempt that ended more than 20 degrees from a clean mask's answer scored at least 4.5 times its loss,
#: while on noisy masks the fits that ended turned had a pose near the truth, or another turned one, within 1.11-1.34
#: of their loss and the right fits none below 1.41: the masks' unexplained pixels put a floor under every loss
#: (docs/any-manipulator.md, "The ambiguous flag").
AMBIGUITY_LOSS_RATIO = 1.35


def _rotation_angles_deg(R: np.ndarray, R_ref: np.ndarray) -> np.ndarray:
    """Angles ``(N,)`` in degrees between rotations ``R (N, 3, 3)`` and ``R_ref (3, 3)``."""
    cos = (np.einsum("sij,ij->s", R, R_ref) - 1.0) / 2.0  # trace(R_s^T R_ref) = 1 + 2 cos(angle)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def pose_ambiguity(result: "PoseResult", *, min_angle_deg: float = 20.0,
                   loss_ratio: float = AMBIGUITY_LOSS_RATIO) -> PoseAmbiguity:
    """The lowest-loss pose that ended more than ``min_angle_deg`` away in rotation from the answer, among the
    returned fit's starts (``starts_final_loss``, against the answer's start's) and the other attempts' final
    poses (``other_attempts_loss_ratio``), and whether its loss is within ``loss_ratio`` times the answer's
    (``AMBIGUITY_LOSS_RATIO`` by default, chosen by measurement)."""
    check_positive(min_angle_deg, "min_angle_deg")
    if not loss_ratio >= 1.0:
        raise ConfigError(f"loss_ratio: expected >= 1, got {loss_ratio}")
    R_best = result.T_cam_root[:3, :3]
    angles = _rotation_angles_deg(result.T_cam_root_starts[:, :3, :3], R_best)  # (S,)
    losses = np.where(np.isfinite(result.starts_final_loss), result.starts_final_loss, np.inf)
    best_loss = float(losses[result.best_start]) if math.isfinite(losses[result.best_start]) else result.loss
    ratios = losses / best_loss if best_loss > 0 else np.where(losses > best_loss, np.inf, 1.0)
    apart = (angles > min_angle_deg) & np.isfinite(losses) & np.isfinite(angles)
    other_angles = _rotation_angles_deg(result.other_attempts_T_cam_root[:, :3, :3], R_best)  # (A,)
    other_ratios = np.where(np.isfinite(result.other_attempts_loss_ratio), result.other_attempts_loss_ratio, np.inf)
    other_apart = (other_angles > min_angle_deg) & np.isfinite(other_ratios) & np.isfinite(other_angles)
    candidates = [(float(ratios[s]), s, -1) for s in np.flatnonzero(apart)]
    candidates += [(float(other_ratios[a]), -1, a) for a in np.flatnonzero(other_apart)]
    if not candidates:
        return PoseAmbiguity(ambiguous=False, runner_up_start=-1, runner_up_T_cam_root=np.full((4, 4), np.nan),
                             runner_up_loss=math.inf, rotation_deg=math.nan)  # fmt: skip
    ratio, start, attempt = min(candidates)
    if start >= 0:
        T, loss, angle = result.T_cam_root_starts[start].copy(), float(losses[start]), float(angles[start])
    else:
        T, angle = result.other_attempts_T_cam_root[attempt].copy(), float(other_angles[attempt])
        loss = ratio * best_loss
    return PoseAmbiguity(ambiguous=bool(ratio <= loss_ratio), runner_up_start=int(start),
                         runner_up_attempt=int(attempt), runner_up_T_cam_root=T, runner_up_loss=loss,
                         runner_up_loss_ratio=ratio, rotation_deg=angle)  # fmt: skip


def estimate_pose(
    mask: np.ndarray,
    model: ManipulatorModel,
    joint_angles: torch.Tensor,
    camera: Camera,
    config: PoseFitConfig = PoseFitConfig(),
    *,
    initial_T_cam_root: np.ndarray | None = None,
    initial_moments: Mapping[str, AdamMoments] | None = None,
) -> PoseResult:
    """Estimate ``T_cam_root`` from a robot mask and the joint readings.

    The mask is undistorted with the camera's coefficients (``pipeline.camera.undistort_image``), then fitted at
    ``config.working_max_side`` (see the module docstring); the answer is in the full-resolution camera frame.

    Args:
        mask: ``(H, W)`` bool, True on the robot, the camera's size.
        model: the robot as rendered (``pipeline.robots.load_urdf_robot``).
        joint_angles: ``(J,)`` joint values in the order of ``model.joint_names``, rad or m.
        camera: the camera that took the image (any size; distortion allowed).
        config: fit settings.
        initial_T_cam_root: ``(4, 4)`` a pose to start from (e.g. the previous video frame's), in the undistorted
            camera frame, the root in front of the camera; one start then runs from it (no random candidates, no
            retries, no boundary refits). ``None`` meaning *no prior*: the random multi-start of the module docstring.
        initial_moments: with ``initial_T_cam_root``, Adam's state its first stage begins with (the last frame's
            ``PoseResult.moments``, ``pipeline.track``'s ``PoseTrackConfig.carry_moments``), or ``None``: zeros.

    Returns:
        PoseResult.

    Raises:
        ShapeError: the mask is not an ``(H, W)`` bool array or is empty (also after undistortion), or
            ``joint_angles`` has the wrong shape or non-finite values.
        ConfigError: the mask's size is not the camera's.
        PipelineError: no start produced a finite loss (the pose is never NaN).
    """
    t0 = time.perf_counter()
    check_mask(mask)
    check_image_matches_camera(mask.shape, camera)
    q = _check_joint_angles(joint_angles, model)
    config = config.for_geometry(model.primitive)
    initial = None
    if initial_T_cam_root is not None:
        initial = np.asarray(initial_T_cam_root, dtype=np.float64)
        if initial.shape != (4, 4) or not np.isfinite(initial).all():
            raise ShapeError(f"initial_T_cam_root: expected a finite (4, 4) transform, got {initial.shape}")
        config = dataclasses.replace(config, retries=0, boundary_refits=0)
    mask, camera = undistort_image(mask, camera, is_mask=True)
    if not mask.any():
        raise ShapeError("mask is empty after undistortion: the robot lies outside the undistorted image")
    retry_weight = config.weight_hidden if config.retry_weight_hidden is None else config.retry_weight_hidden
    retry_config = dataclasses.replace(config, weight_hidden=retry_weight)
    with single_torch_thread():  # see the module docstring (Rendering)
        scene = _Scene.build(model, q, config)
        asks = (model.outline is not None and model.primitive != "cad" and config.retries > 0
                and config.retry_outline_loss is not None)
        may_polish = model.outline is not None and _may_polish_outline(config)
        offset_asks = model.outline is not None and initial is not None and config.offset_polish_loss is not None
        outline = _OutlineCheck(model, q, config) if asks or may_polish or offset_asks else None
        result, polished, found_px = _fit_and_retry(mask, scene, q, camera, config, t0, initial, outline,
                                                    moments=initial_moments)
        found = result
        level_px, refits = 0.0, 0  # found_px: the last fit's offset from its mask, by its own geometry's polish
        # a refit runs as the fit kept ran (its hidden weight, the outline polish where it had one), no retries
        refit_config = dataclasses.replace(config, retries=0, weight_hidden=result.weight_hidden,
                                           outline_polish=polished)
        while (config.polish_boundary_offset and refits < config.boundary_refits
               and abs(found_px) >= config.boundary_refit_px
               and abs(level_px + found_px) <= config.boundary_offset_max_px):  # beyond it, the pose is at fault
            level_px += found_px  # the offsets found so far added up (module docstring, Boundary refits)
            logger.info("pose fit: the mask's edge lies %.2f px outside the robot's, fitting its level set", level_px)
            level = _mask_level_set(mask, level_px * max(mask.shape) / config.reference_side)
            found, _, found_px = _fit_and_retry(level, scene, q, camera, refit_config, t0, initial, outline)
            refits += 1
            found = dataclasses.replace(found, boundary_offset_px=level_px + found.boundary_offset_px)  # from the mask
            better = _better(found, result, mask, scene, camera, retry_config)
            kept, rival = (found, result) if better else (result, found)
            result = _with_rival(kept, rival, mask, scene, camera, retry_config)
        return dataclasses.replace(result, seconds=time.perf_counter() - t0, boundary_refits=refits)


def _may_polish_outline(config: PoseFitConfig) -> bool:
    """Whether a fit under ``config`` may end with the outline polish (``outline_polish``; ``None``: after a retry,
    or when ``outline_polish_loss`` is set)."""
    if config.outline_polish is not None:
        return config.outline_polish
    return config.retries > 0 or config.outline_polish_loss is not None


def _fit_and_retry(mask: np.ndarray, scene: "_Scene", q: torch.Tensor, camera: Camera, config: PoseFitConfig,
                   t0: float, initial: np.ndarray | None, outline: "_OutlineCheck | None",
                   moments: Mapping[str, AdamMoments] | None = None) -> tuple[PoseResult, bool, float]:
    """:func:`estimate_pose`'s fit of the (undistorted) ``mask`` with its retries and the outline's question and
    polish (module docstring, Retries), ``config`` resolved for the geometry; ``outline`` where the model has one
    and the retry asks it or the outline polish may run. Returns the result, whether the outline polished it, and
    the boundary offset the fit's own geometry's polish found before the outline's polish (the boundary refit's
    question: module docstring, Boundary refits)."""
    retry_weight = config.weight_hidden if config.retry_weight_hidden is None else config.retry_weight_hidden
    retry_config = dataclasses.replace(config, weight_hidden=retry_weight)
    offset_if = None
    if (outline is not None and initial is not None and config.offset_polish_loss is not None
            and not config.polish_boundary_offset):
        def offset_if(R: torch.Tensor, placement: torch.Tensor) -> bool:  # the outline's question, before the polish
            T = scene.T_cam_root(R[None], placement[None])[0].numpy()
            explained = _explained_mask(mask, _silhouette_of(scene, R, placement, torch.zeros_like(
                scene.verts_root), camera), config) if config.drop_unexplained else mask
            return _loss_at(outline.scene, explained, camera, T, config) > config.offset_polish_loss
    result = _fit(mask, scene, q, camera, config, t0, initial, offset_if=offset_if, moments=moments)
    attempts, given_up, finished = 1, 0, [result]
    asks = outline is not None and not outline.refines and config.retries > 0 and config.retry_outline_loss is not None
    may_polish = outline is not None and _may_polish_outline(config)
    while attempts <= config.retries and (result.loss > config.retry_loss if not asks
                                          else outline.loss(mask, camera, scene, result) > config.retry_outline_loss):
        logger.info("pose fit: loss %.3g%s, fitting again (weight_hidden %g)", result.loss,
                    f" > retry_loss {config.retry_loss:.3g}" if not asks else
                    f", its outline's {outline.last:.3g} > retry_outline_loss {config.retry_outline_loss:.3g}",
                    retry_weight)  # fmt: skip
        give_up = None
        if config.retry_compare_stage > 0 and result.weight_hidden == retry_weight:  # stage losses comparable
            k = min(config.retry_compare_stage, len(config.stages)) - 1
            give_up = (k, (1.0 - config.retry_min_gain) * stage_best_losses(result.history, config)[k])
        again = _fit(mask, scene, q, camera, dataclasses.replace(retry_config, seed=config.seed + attempts), t0,
                     give_up_at=give_up)
        attempts += 1
        if again is None:
            given_up += 1
            continue
        finished.append(again)
        if _better(again, result, mask, scene, camera, retry_config):
            result = again
    others = [r for r in finished if r is not result]
    ratios = _loss_ratios(others, result, mask, scene, camera, retry_config)
    gated = (may_polish and attempts == 1 and config.outline_polish is None and config.outline_polish_loss is not None
             and outline.loss(mask, camera, scene, result) > config.outline_polish_loss)
    refined = may_polish and config.outline_polish is None and outline.refines  # a CAD model's finer meshes
    polished = may_polish and (attempts > 1 or bool(config.outline_polish) or gated or refined)
    own_offset_px = result.boundary_offset_px
    if polished:
        result = outline.polish(mask, camera, scene, result)
    elif asks or (may_polish and config.outline_polish_loss is not None):
        result = dataclasses.replace(result, outline_loss=outline.loss(mask, camera, scene, result))
    return dataclasses.replace(
        result, attempts=attempts, retries_given_up=given_up,
        other_attempts_T_cam_root=np.array([r.T_cam_root for r in others]).reshape(-1, 4, 4),
        other_attempts_loss_ratio=ratios), polished, own_offset_px


class _OutlineCheck:
    """The loss of a fit's pose drawn with the model's ``outline`` (its visual meshes), the retry's question where
    the fit draws link hulls (module docstring, Retries)."""

    def __init__(self, model: ManipulatorModel, q: torch.Tensor, config: PoseFitConfig) -> None:
        self.scene = _Scene.build(model.outline, q, config)
        self.config = config
        self.refines = model.primitive == "cad"  # the outline: the model's own meshes, finer
        self.last = math.nan
        self._asked: tuple[PoseResult, float] | None = None
        self._set: tuple[PoseResult, PoseFitConfig, np.ndarray] | None = None  # the last result's setting

    def loss(self, mask: np.ndarray, camera: Camera, scene: _Scene, result: PoseResult) -> float:
        """The outline's last-stage loss at ``result``'s pose under its hidden weight, against the (undistorted)
        ``mask`` less the components the fit's own silhouette does not come near (``drop_unexplained``)."""
        if self._asked is not None and self._asked[0] is result:  # asked already (the answer's, after the retries)
            return self._asked[1]
        config, mask = self._setting(mask, camera, scene, result)
        self.last = _loss_at(self.scene, mask, camera, result.T_cam_root, config)
        self._asked = (result, self.last)
        return self.last

    def polish(self, mask: np.ndarray, camera: Camera, scene: _Scene, result: PoseResult) -> PoseResult:
        """``result`` polished drawn with the outline (``PoseFitConfig.outline_polish``): the polish of a CAD fit
        from its pose, its boundary offset fitted."""
        config, mask = self._setting(mask, camera, scene, result)
        rounds, patience, min_step = SCHEDULE_BY_GEOMETRY["cad"][1:4]
        steps = config.polish_newton_steps
        if self.refines:  # from the answer of a CAD polish: a short one (CAD_OUTLINE_POLISH)
            steps, rounds = min(steps, CAD_OUTLINE_POLISH[0]), min(rounds, CAD_OUTLINE_POLISH[1])
        config = dataclasses.replace(config, polish_boundary_offset=True, polish_rounds=rounds if config.polish_rounds
                                     else 0, polish_newton_steps=steps, polish_newton_patience=patience,
                                     polish_min_step_px=min_step)
        R, placement = _placement_of(self.scene, result.T_cam_root)
        drawn = self.scene
        if not drawn.cull and config.cull_back_faces and config.cull_open_tolerance > 0:
            at = (R[0], placement[0], torch.zeros_like(drawn.verts_root), camera)
            drawn = _cull_if_unseen(drawn, *at, _silhouette_of(drawn, *at), config.cull_open_tolerance)
        R, placement, loss, boundary_px, depth_std_m = _polished(
            drawn, mask, camera, R[0], placement[0], None, config, estimate_from=torch.zeros_like(drawn.verts_root))
        self.last = loss
        return dataclasses.replace(result, T_cam_root=self.scene.T_cam_root(R[None], placement[None])[0].numpy(),
                                   boundary_offset_px=boundary_px, depth_std_m=depth_std_m, outline_loss=loss)

    def _setting(self, mask: np.ndarray, camera: Camera, scene: _Scene, result: PoseResult
                 ) -> tuple[PoseFitConfig, np.ndarray]:
        """The config at ``result``'s hidden weight and the mask less what its silhouette leaves unexplained (one
        full-resolution render; kept for the same result: the question and the polish both need it)."""
        if self._set is not None and self._set[0] is result:
            return self._set[1], self._set[2]
        config = dataclasses.replace(self.config, weight_hidden=result.weight_hidden)
        if config.drop_unexplained:
            R, placement = _placement_of(scene, result.T_cam_root)
            silhouette = _silhouette_of(scene, R[0], placement[0], torch.zeros_like(scene.verts_root), camera)
            mask = _explained_mask(mask, silhouette, config)
        self._set = (result, config, mask)
        return config, mask


def _with_rival(kept: PoseResult, rival: PoseResult, mask: np.ndarray, scene: _Scene, camera: Camera,
                config: PoseFitConfig) -> PoseResult:
    """``kept`` with the boundary refit's other fit ``rival`` (the one not kept) among its other attempts, its loss
    over ``kept``'s as :func:`_better` compared them (:func:`_loss_ratios`; a refit runs under the kept fit's hidden
    weight, so each fit's own loss, against its own level set of the mask), so that :func:`pose_ambiguity` sees the
    basin it ended in. The rival's own other attempts are not carried: their ratios may be under another loss (the
    retry's hidden weight)."""
    return dataclasses.replace(
        kept, other_attempts_T_cam_root=np.concatenate([kept.other_attempts_T_cam_root, rival.T_cam_root[None]]),
        other_attempts_loss_ratio=np.concatenate([kept.other_attempts_loss_ratio,
                                                  _loss_ratios([rival], kept, mask, scene, camera, config)]))


def _loss_ratios(others: list[PoseResult], kept: PoseResult, mask: np.ndarray, scene: _Scene, camera: Camera,
                 config: PoseFitConfig) -> np.ndarray:
    """``(A,)`` the losses of the attempts ``others`` over the ``kept`` one's, under the loss :func:`_better`
    compares them with: their own when every attempt ran under one hidden weight, else ``config``'s
    (:func:`_final_loss`)."""
    if not others:
        return np.zeros(0)
    if all(r.weight_hidden == kept.weight_hidden for r in others):
        scores, base = [r.loss for r in others], kept.loss
    else:
        scores = [_final_loss(r, mask, scene, camera, config) for r in others]
        base = _final_loss(kept, mask, scene, camera, config)
    return np.array([score / base if base > 0 else (math.inf if score > base else 1.0) for score in scores])


def _better(new: PoseResult, kept: PoseResult, mask: np.ndarray, scene: _Scene, camera: Camera,
            config: PoseFitConfig) -> bool:
    """Whether a retry's fit ``new`` explains the (undistorted) mask better than the ``kept`` one: by their own
    losses when both were fitted under ``config``'s loss, else (``retry_weight_hidden``) by both poses' losses under
    ``config`` (:func:`_final_loss`: the hidden weight of the retry)."""
    if new.weight_hidden == kept.weight_hidden:
        return new.loss < kept.loss
    return _final_loss(new, mask, scene, camera, config) < _final_loss(kept, mask, scene, camera, config)


def _final_loss(result: PoseResult, mask: np.ndarray, scene: _Scene, camera: Camera, config: PoseFitConfig
                ) -> float:
    """:func:`_loss_at` of a fit's pose, vertex offsets and boundary offset."""
    return _loss_at(scene, mask, camera, result.T_cam_root, config, result.vertex_offsets, result.boundary_offset_px)


def _loss_at(scene: _Scene, mask: np.ndarray, camera: Camera, T_cam_root: np.ndarray, config: PoseFitConfig,
             vertex_offsets: np.ndarray | None = None, boundary_px: float = 0.0) -> float:
    """The last stage's loss under ``config``, at the working resolution, of the pose ``T_cam_root (4, 4)`` with
    ``vertex_offsets (V, 3)`` (``None``: none), against the level set ``boundary_px`` (reference pixels) inside the
    edge of the undistorted ``mask``."""
    stage = config.stages[-1]
    fitted = _mask_level_set(mask, boundary_px * max(mask.shape) / config.reference_side)
    target = _StageTarget.build(fitted, camera, working_size(camera.image_size, config.working_max_side), stage,
                                config)
    R, placement = _placement_of(scene, T_cam_root)
    pose = torch.cat([torch.zeros(1, 3, dtype=torch.float64), placement], 1)
    offsets = None if stage.hull or vertex_offsets is None else torch.from_numpy(vertex_offsets)[None]
    with torch.no_grad():
        return float(_total_loss(scene, target, R, pose, stage.hull, offsets, config)[0])


def stage_best_losses(history: np.ndarray, config: PoseFitConfig) -> list[float]:
    """The lowest loss of any start in each stage of ``config`` (``history``: ``PoseResult.history``, ``(N, S)``, NaN
    where not run); a retry compares them (module docstring, Retries). ``config.iterations`` may be ``None``: the
    history's length is the iterations the fit ran."""
    if config.iterations is None:
        config = dataclasses.replace(config, iterations=len(history))
    ends = np.cumsum(config.stage_iterations())
    return [float(np.nanmin(history[a:b], initial=math.inf)) for a, b in zip([0, *ends[:-1]], ends)]


def _fit(mask: np.ndarray, scene: _Scene, q: torch.Tensor, camera: Camera, config: PoseFitConfig,
         t0: float, initial: np.ndarray | None = None, give_up_at: tuple[int, float] | None = None,
         offset_if: Callable[[torch.Tensor, torch.Tensor], bool] | None = None,
         moments: Mapping[str, AdamMoments] | None = None) -> PoseResult | None:
    """:func:`estimate_pose` on checked inputs: ``mask`` undistorted, ``camera`` without distortion, ``scene`` the
    robot at joints ``q``; ``initial`` a ``(4, 4)`` pose to start from alone, or ``None`` for the random
    multi-start. ``give_up_at = (k, loss)``: return ``None`` when the best loss of stage ``k`` (0-based) is not below
    ``loss`` (a retry, module docstring). ``offset_if(R (3, 3), placement (3,))``: whether the polish fits the
    boundary offset after all, asked at the answer before it (``PoseFitConfig.offset_polish_loss``)."""
    working = working_size(camera.image_size, config.working_max_side)
    if initial is None:
        init_stage = PoseStage(fraction=1.0, scale=min(1.0, config.init_max_side / max(working)), keep=config.starts,
                               sigma_px2=1.0)
        rotation_ref, placement = _initial_starts(scene, _StageTarget.build(mask, camera, working, init_stage, config),
                                                  config)  # (S, 3, 3), (S, 3)
    else:
        rotation_ref, placement = _placement_of(scene, initial)  # (1, 3, 3), (1, 3)
    S = rotation_ref.shape[0]
    pose = torch.cat([torch.zeros(S, 3, dtype=torch.float64), placement], 1)  # (S, 6) = (w, a, b, log z)
    offsets = torch.zeros(S, *scene.verts_root.shape, dtype=torch.float64)  # (S, V, 3) link frames
    alive = torch.arange(S)  # the starts still optimised
    best_loss = torch.zeros(S, dtype=torch.float64)
    history = np.full((config.iterations, S), np.nan)
    trajectory = np.full((config.iterations, S, 4, 4), np.nan) if config.record_trajectory else None
    area = int(mask.sum())
    boundary_px = 0.0  # the mask's edge outside the robot's, reference pixels (fit_boundary_offset)
    done = 0
    for k, (stage, n) in enumerate(zip(config.stages, config.stage_iterations())):
        current = rotvec_to_rotmat(pose[alive, :3]) @ rotation_ref[alive]  # (A, 3, 3) the alive starts' rotations
        if k > 0 and config.rank_by_meshes and config.stages[k - 1].hull and not stage.hull and len(alive) > 1:
            # the hulls chose these basins; the link meshes' loss, at the poses the hulls reached, picks among them
            probe = _StageTarget.build(mask, camera, working, stage, config)
            zero = torch.cat([torch.zeros(len(alive), 3, dtype=torch.float64), pose[alive, 3:]], 1)
            with torch.no_grad():
                best_loss[alive] = _total_loss(scene, probe, current, zero, False, offsets[alive], config)
        if stage.keep < len(alive):
            chosen = _kept_starts(current, best_loss[alive], stage.keep, config.keep_separation_deg)
            alive, current = alive[chosen], current[chosen]
        rotation_ref[alive] = current  # re-base: w -> 0
        pose[alive, :3] = 0.0
        check_culling = not stage.hull and not scene.cull and config.cull_back_faces and config.cull_open_tolerance > 0
        fitted = mask  # the mask this stage fits: the level set delta inside its edge with fit_boundary_offset
        uses_silhouette = k > 0 and (config.drop_unexplained or config.fit_boundary_offset)
        if check_culling or uses_silhouette:  # the best start's silhouette, every face drawn
            lead = int(alive[torch.argmin(best_loss[alive])])
            at = (rotation_ref[lead], pose[lead, 3:], offsets[lead], camera)
            silhouette = _silhouette_of(scene, *at)
            if check_culling:
                scene = _cull_if_unseen(scene, *at, silhouette, config.cull_open_tolerance)
        if uses_silhouette:
            if config.drop_unexplained:
                mask = _explained_mask(mask, silhouette, config)
            fitted = mask
            if config.fit_boundary_offset and not stage.hull:  # hull stages only look for the basin
                boundary_px = _boundary_offset(mask, silhouette, config)
                fitted = _mask_level_set(mask, boundary_px * max(mask.shape) / config.reference_side)
        target = _StageTarget.build(fitted, camera, working, stage, config)
        R_ref = rotation_ref[alive]
        groups = {"pose": ParamGroup(init=pose[alive], lr=config.lr_pose * stage.lr_scale)}
        if not stage.hull and config.lr_offsets > 0:
            groups["offsets"] = ParamGroup(init=offsets[alive], lr=config.lr_offsets * stage.lr_scale)

        def loss_fn(p: Mapping[str, torch.Tensor], iteration: int, target=target, R_ref=R_ref, alive=alive,
                    done=done, hull=stage.hull) -> torch.Tensor:
            if trajectory is not None:
                with torch.no_grad():
                    R = rotvec_to_rotmat(p["pose"][:, :3]) @ R_ref
                    trajectory[done + iteration, alive.numpy()] = scene.T_cam_root(R, p["pose"][:, 3:]).numpy()
            return _total_loss(scene, target, R_ref, p["pose"], hull, p.get("offsets"), config)

        result = fit(groups, loss_fn, iterations=n, description=f"pose {target.size[1]}x{target.size[0]}",
                     final_lr_factor=stage.final_lr_factor, moments=moments if k == 0 else None)
        pose[alive] = result.best_params["pose"]
        if "offsets" in groups:
            offsets[alive] = result.best_params["offsets"]
        best_loss[alive] = result.best_loss
        history[done:done + n, alive.numpy()] = result.history.numpy()
        done += n
        logger.info("stage %dx%d: %d starts, %d iterations, best loss %.4g, %.2f s", target.size[1],
                    target.size[0], len(alive), n, float(result.best_loss.min()), result.seconds)
        if give_up_at is not None and k == give_up_at[0] and not float(result.best_loss.min()) < give_up_at[1]:
            logger.info("retry given up after stage %d: best loss %.4g, not below %.4g", k + 1,
                        float(result.best_loss.min()), give_up_at[1])  # fmt: skip
            return None

    rotation = rotvec_to_rotmat(pose[:, :3]) @ rotation_ref  # (S, 3, 3)
    best = int(alive[torch.argmin(best_loss[alive])])
    loss_before_polish = float(best_loss[best])
    depth_std_m = math.nan  # the polish's estimate
    if (config.polish_newton_steps or config.polish_rounds) and math.isfinite(loss_before_polish):
        if config.stages[-1].straight_through:
            last_offsets = offsets[best] if not config.stages[-1].hull and config.lr_offsets > 0 else None
            estimated = config.fit_boundary_offset or config.polish_boundary_offset
            polish_config = config
            if not estimated and offset_if is not None and offset_if(rotation[best], pose[best, 3:]):
                polish_config, estimated = dataclasses.replace(config, polish_boundary_offset=True), True
            rotation[best], pose[best, 3:], polished, polished_px, depth_std_m = _polished(
                scene, mask, camera, rotation[best], pose[best, 3:], last_offsets, polish_config,
                estimate_from=offsets[best] if estimated else None, boundary_px=boundary_px)
            pose[best, :3] = 0.0
            if polished_px != boundary_px or estimated:  # every start's final loss below against that level set
                boundary_px = polished_px
                fitted = _mask_level_set(mask, boundary_px * max(mask.shape) / config.reference_side)
                target = _StageTarget.build(fitted, camera, working, config.stages[-1], config)
            # the polish moves only to a lower windowed loss; a pose it kept may score the last bit higher there
            best_loss[best] = min(polished, loss_before_polish)
        else:
            logger.info("polish skipped: the last stage's loss is not the hard silhouette's (straight_through)")
    with torch.no_grad():  # every start's best parameters under the last stage's loss
        final_pose = torch.cat([torch.zeros(S, 3, dtype=torch.float64), pose[:, 3:]], 1)
        final_loss = _total_loss(scene, target, rotation, final_pose, config.stages[-1].hull, offsets, config)
    final_loss = torch.where(torch.isfinite(final_loss), final_loss, math.inf)
    T_starts = scene.T_cam_root(rotation, pose[:, 3:]).numpy()
    if not np.isfinite(T_starts[best]).all() or not math.isfinite(float(best_loss[best])):
        raise PipelineError("pose fit failed: no start reached a finite loss (check the mask and the joint readings)")
    return PoseResult(
        T_cam_root=T_starts[best],
        loss=float(best_loss[best]),
        history=history,
        starts_final_loss=final_loss.numpy(),
        T_cam_root_starts=T_starts,
        best_start=best,
        vertex_offsets=offsets[best].numpy(),
        joint_angles=q.numpy(),
        iterations=config.iterations,
        seconds=time.perf_counter() - t0,
        image_size=camera.image_size,
        working_size=target.size,
        dropped_fraction=1.0 - float(mask.sum()) / area,
        trajectory=trajectory,
        loss_before_polish=loss_before_polish,
        boundary_offset_px=boundary_px,
        weight_hidden=config.weight_hidden,
        depth_std_m=depth_std_m,
        moments=result.moments_of(),
    )


def pose_loss_at(mask: np.ndarray, model: ManipulatorModel, joint_angles: torch.Tensor, camera: Camera,
                 T_cam_root: np.ndarray, config: PoseFitConfig = PoseFitConfig()) -> float:
    """The last stage's loss (``PoseResult.loss``'s scale) of a given pose, without vertex offsets: e.g. to compare
    the truth with an estimate. The mask is undistorted as :func:`estimate_pose` does; components it would drop as
    unexplained are kept.

    Args:
        mask: ``(H, W)`` bool, the camera's size.
        joint_angles: ``(J,)`` in the order of ``model.joint_names``.
        T_cam_root: ``(4, 4)`` in the undistorted camera frame, metres.
    """
    check_mask(mask)
    check_image_matches_camera(mask.shape, camera)
    q = _check_joint_angles(joint_angles, model)
    mask, camera = undistort_image(mask, camera, is_mask=True)
    return _loss_at(_Scene.build(model, q, config), mask, camera, T_cam_root, config)


def estimate_pose_from_readings(
    mask: np.ndarray,
    model: ManipulatorModel,
    joint_readings: Mapping[str, float],
    camera: Camera,
    config: PoseFitConfig = PoseFitConfig(),
    *,
    zero_missing: bool = False,
) -> PoseResult:
    """:func:`estimate_pose` with joint readings by name (``model.joint_vector`` checks and orders them)."""
    return estimate_pose(mask, model, model.joint_vector(joint_readings, zero_missing=zero_missing), camera, config)


@dataclass(frozen=True, kw_only=True)
class StaticCameraConfig:
    """Settings of :func:`refine_static_camera`.

    Fields:
        iterations: Adam steps of the joint refinement.
        max_frames: at most this many frames take part, evenly spread over those given.
        trim_fraction: share of the frames whose losses are left out of the sum at every step (the highest ones:
            a frame whose mask is wrong, or whose joint readings are), in [0, 0.5].
        candidates: at most this many of the starting poses (evenly spread) are scored on all frames; the
            refinement starts from the best.
        working_max_side: longest side of the working resolution (pixels).
        lr_pose: Adam learning rate of ``(w, a, b, log z)``, decaying to ``lr_pose * final_lr_factor``.
        final_lr_factor: see ``lr_pose``.
        sigma_px2: softness of the silhouette, squared working pixels.
        fit: the loss weights, ``gamma``, ``reference_side``, ``cutoff_eps`` and ``cull_back_faces`` of a
            single-frame fit, and for the polish ``polish_boundary_offset`` and ``boundary_offset_max_px`` (its
            other fields are not used); the appearance term kept (weight 1), as measured
            (``docs/tracking.md``), unlike the single-image default.
        polish_steps: Levenberg-Marquardt steps on the frames' hard silhouettes after the Adam steps, each taken
            only where it lowers the trimmed loss; they end early after two in a row without (0: none).
        polish_step_px: the polish's finite-difference step: the image motion (working pixels) of a unit step.
        polish_boundary_offset: the polish also fits each frame's boundary offset (a segmenter's outline bias,
            as ``PoseFitConfig.polish_boundary_offset`` for one frame); ``None``: as ``fit`` says (itself ``None``
            by default: on with CAD meshes, off with hulls and primitives, whose outlines differ from the robot's).
        coverage_target: the frames' mask terms target each working pixel's coverage
            (``PoseFitConfig.coverage_target``; this field, not ``fit``'s, decides): on 14 tuning videos the
            estimate was nearer the truth on 9 with it and farther on 3 (``docs/tracking.md``).
        outline_polish: for a model with an ``outline`` (its visual meshes kept beside link hulls,
            ``ManipulatorModel.outline``), the polish draws the outline instead of the hulls, each frame's boundary
            offset fitted unless ``polish_boundary_offset`` is ``False`` (as a CAD polish): a hull is wider than
            its link and biases the depth. No effect without an outline or a polish, nor on a CAD model (whose outline
            is its own meshes within 1 mm: the static refinement was not re-timed with them). On by default since
            session 49: on 15 tuning videos (Panda, UR5, Baxter; alternating noisy masks, the shipped network's, and
            masks dilated or eroded by a pixel on every frame, a segmenter's steady bias) the estimate was nearer
            on 10, its mean error 16.2 mm against 27.8 with the hulls; under a steady bias the hulls' estimate is
            farther than the median single-frame fit (``docs/tracking.md``).
    """

    iterations: int = 100
    max_frames: int = 24
    trim_fraction: float = 0.25
    candidates: int = 8
    working_max_side: int = 320
    lr_pose: float = 3e-3
    final_lr_factor: float = 0.1
    sigma_px2: float = 0.5
    fit: PoseFitConfig = PoseFitConfig(weight_appearance=1.0)
    polish_steps: int = 10
    polish_step_px: float = 1.0
    polish_boundary_offset: bool | None = None
    coverage_target: bool = True
    outline_polish: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.outline_polish, bool):
            raise ConfigError(f"StaticCameraConfig.outline_polish: expected True or False, got "
                              f"{self.outline_polish!r}")
        for name in ("iterations", "max_frames", "candidates", "working_max_side"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"StaticCameraConfig.{name}: expected an int >= 1, got {value!r}")
        if isinstance(self.polish_steps, bool) or not isinstance(self.polish_steps, int) or self.polish_steps < 0:
            raise ConfigError(f"StaticCameraConfig.polish_steps: expected an int >= 0, got {self.polish_steps!r}")
        check_positive(self.polish_step_px, "StaticCameraConfig.polish_step_px")
        if self.polish_boundary_offset is not None and not isinstance(self.polish_boundary_offset, bool):
            raise ConfigError(f"StaticCameraConfig.polish_boundary_offset: expected True, False or None (by the "
                              f"link geometry), got {self.polish_boundary_offset!r}")
        if not 0.0 <= float(self.trim_fraction) <= 0.5:
            raise ConfigError(f"StaticCameraConfig.trim_fraction: expected a number in [0, 0.5], got "
                              f"{self.trim_fraction!r}")
        check_positive(self.lr_pose, "StaticCameraConfig.lr_pose")
        check_positive(self.final_lr_factor, "StaticCameraConfig.final_lr_factor")
        check_positive(self.sigma_px2, "StaticCameraConfig.sigma_px2")
        if not isinstance(self.fit, PoseFitConfig):
            raise ConfigError(f"StaticCameraConfig.fit: expected a PoseFitConfig, got {type(self.fit).__name__}")


@dataclass(frozen=True, kw_only=True, eq=False)
class StaticCameraResult:
    """Outcome of :func:`refine_static_camera`.

    Fields:
        T_cam_root: ``(4, 4)`` the one camera-to-root pose of all frames (undistorted camera frame), metres.
        loss: the trimmed mean of the frames' losses at that pose.
        frame_losses: ``(F,)`` each frame's loss at that pose (order of ``frames``).
        frames: the indices (into the sequences given) of the ``F`` frames that took part.
        trimmed: those of ``frames`` whose losses were left out at the end (the highest).
        start: index (into the starting poses given) of the pose the refinement started from.
        iterations: Adam steps.
        seconds: wall time.
        loss_before_polish: the trimmed loss after the Adam steps, before the polish.
        polish_steps: the polish's steps taken.
        boundary_offsets_px: ``(F,)`` each frame's fitted boundary offset (reference pixels, as
            ``PoseResult.boundary_offset_px``; zeros unless fitted); ``loss`` and ``frame_losses`` are at these
            offsets.
        outline: the polish drew the model's ``outline`` (``StaticCameraConfig.outline_polish``); ``loss`` and
            ``frame_losses`` are then the outline's, ``loss_before_polish`` the link geometry's.
    """

    T_cam_root: np.ndarray
    loss: float
    frame_losses: np.ndarray
    frames: tuple[int, ...]
    trimmed: tuple[int, ...]
    start: int
    iterations: int
    seconds: float
    loss_before_polish: float
    polish_steps: int
    boundary_offsets_px: np.ndarray
    outline: bool = False


def refine_static_camera(
    masks: Sequence[np.ndarray],
    joint_angles: Sequence[torch.Tensor],
    model: ManipulatorModel,
    camera: Camera,
    initial_T_cam_root: Sequence[np.ndarray],
    config: StaticCameraConfig = StaticCameraConfig(),
) -> StaticCameraResult:
    """One ``T_cam_root`` for many frames of a camera that does not move relative to the robot's root.

    Every frame contributes its mask and its joint readings: the loss of a pose is the trimmed mean of the frames'
    single-frame losses (``L_mask + L_dist + L_app``, each divided by its mask's area) with the highest
    ``trim_fraction`` of them left out, so that a frame whose mask is wrong does not pull the answer. The pose is
    ``(w, a, b, log z)`` about one centre (the mean of the frames' mesh centres in the root frame), optimised by
    Adam on the straight-through silhouettes of all frames rendered as one batch, the lowest loss kept; it starts
    from the best of the given poses (e.g. the frames' own estimates), scored on all frames. Then
    ``polish_steps`` Levenberg-Marquardt steps on the kept frames' hard silhouettes (:func:`_polish_static`), each
    taken only where it lowers the trimmed loss: the Adam steps on soft gradients stop short of the loss's minimum.

    Args:
        masks: ``F`` masks ``(H, W)`` bool, the camera's size (frames where the robot is visible).
        joint_angles: ``F`` tensors ``(J,)`` (order of ``model.joint_names``), one per mask.
        model: the robot.
        camera: the camera (distortion allowed; the answer is in its undistorted frame).
        initial_T_cam_root: at least one ``(4, 4)`` starting pose.
        config: settings.

    Raises:
        ShapeError: no frame, masks and readings of different counts, an empty mask, bad readings or poses.
    """
    t0 = time.perf_counter()
    if len(masks) == 0 or len(masks) != len(joint_angles):
        raise ShapeError(f"masks, joint_angles: expected the same number (>= 1) of each, got {len(masks)} and "
                         f"{len(joint_angles)}")
    starts = [np.asarray(T, dtype=np.float64) for T in initial_T_cam_root]
    if not starts or any(T.shape != (4, 4) or not np.isfinite(T).all() for T in starts):
        raise ShapeError("initial_T_cam_root: expected at least one finite (4, 4) transform")
    chosen = _evenly(len(masks), config.max_frames)
    starts_chosen = _evenly(len(starts), config.candidates)
    fit_config = dataclasses.replace(config.fit, coverage_target=config.coverage_target)
    stage = PoseStage(fraction=1.0, scale=1.0, keep=1, sigma_px2=config.sigma_px2)
    targets, fulls = [], []
    for i in chosen:
        frame_mask = masks[i]  # read once: a sequence may unpack it on each read
        check_mask(frame_mask)
        check_image_matches_camera(frame_mask.shape, camera)
        mask, undistorted = undistort_image(frame_mask, camera, is_mask=True)
        if not mask.any():
            raise ShapeError(f"masks[{i}]: empty after undistortion (leave out frames without the robot)")
        fulls.append(mask)
        targets.append(_StageTarget.build(mask, undistorted, working_size(undistorted.image_size,
                                                                          config.working_max_side), stage, fit_config))
    q = torch.stack([_check_joint_angles(joint_angles[i], model) for i in chosen])  # (F, J)
    target = targets[0]  # K, size and raster settings are common to all frames
    M = torch.stack([t.mask for t in targets])  # (F, h, w)
    D = torch.stack([t.distance for t in targets])
    W = None if target.weight is None else torch.stack([t.weight for t in targets])
    area = torch.tensor([t.area for t in targets], dtype=torch.float64)  # (F,)
    with single_torch_thread():
        scene = _Scene.build(model, q[0], fit_config)
        verts_root = model.mesh_in_root(q)  # (F, V, 3)
        centre = ((verts_root.min(1).values + verts_root.max(1).values) / 2).mean(0)  # (3,) root frame
        scene = dataclasses.replace(scene, centre=centre)
        F = len(chosen)
        keep = max(1, math.ceil((1.0 - config.trim_fraction) * F - 1e-9))

        def losses_of(verts_root: torch.Tensor, scene: _Scene) -> Callable[..., torch.Tensor]:
            """The frames' losses drawn with ``verts_root (F, V, 3)`` and ``scene``'s faces."""

            def frame_losses(R: torch.Tensor, placement: torch.Tensor, terms: tuple | None = None) -> torch.Tensor:
                """``(F,)`` losses of the pose ``R (3, 3)``, ``placement (3,)``; ``terms``: the frames' ``(mask,
                distance, weight)`` to compare with in place of their masks' (the polish's level sets)."""
                verts = (verts_root - centre) @ R.T + _translation(placement[None])  # (F, V, 3)
                silhouette = _render(verts, scene, target, hull=False)  # (F, h, w)
                mask, distance, weight = (M, D, W) if terms is None else terms
                loss = fit_config.weight_mask * mask_loss(silhouette, mask, weight)
                if fit_config.weight_distance:
                    loss = loss + fit_config.weight_distance * distance_loss(silhouette, distance)
                if fit_config.weight_appearance:
                    loss = loss + fit_config.weight_appearance * appearance_loss(silhouette, M)
                return loss / area

            return frame_losses

        frame_losses = losses_of(verts_root, scene)

        def trimmed(losses: torch.Tensor) -> torch.Tensor:
            return torch.sort(losses).values[:keep].mean()

        scored = []
        with torch.no_grad():
            for k in starts_chosen:
                R, placement = _placement_of(scene, starts[k])
                scored.append((float(trimmed(frame_losses(R[0], placement[0]))), k, R[0], placement[0]))
        _, start, R_ref, placement = min(scored, key=lambda item: item[0])

        def loss_fn(p: Mapping[str, torch.Tensor], iteration: int) -> torch.Tensor:
            R = rotvec_to_rotmat(p["pose"][:, :3])[0] @ R_ref
            return trimmed(frame_losses(R, p["pose"][0, 3:]))[None]

        pose = torch.cat([torch.zeros(3, dtype=torch.float64), placement])[None]  # (1, 6)
        result = fit({"pose": ParamGroup(init=pose, lr=config.lr_pose)}, loss_fn, iterations=config.iterations,
                     description="static camera", final_lr_factor=config.final_lr_factor)
        best = result.best_params["pose"][0]
        R = rotvec_to_rotmat(best[None, :3])[0] @ R_ref
        placement = best[3:]
        with torch.no_grad():
            losses = frame_losses(R, placement)
            loss_before_polish = float(trimmed(losses))
            outline = (config.outline_polish and model.outline is not None and model.primitive != "cad"
                       and config.polish_steps > 0)
            if outline:  # the polish draws the visual meshes (StaticCameraConfig.outline_polish)
                verts_root = model.outline.mesh_in_root(q)
                scene = dataclasses.replace(_Scene.build(model.outline, q[0], fit_config), centre=centre)
                frame_losses = losses_of(verts_root, scene)
                losses = frame_losses(R, placement)
            offsets_fitted = config.polish_boundary_offset
            if offsets_fitted is None:  # as a single-frame fit with these settings and this geometry does
                offsets_fitted = bool(fit_config.for_geometry("cad" if outline else model.primitive)
                                      .polish_boundary_offset)
            levels = [_LevelSets(t.mask.numpy() >= 0.5, fit_config,  # at 0: the target (coverage or not)
                                 (t.size, full) if fit_config.coverage_target else None)
                      for t, full in zip(targets, fulls)] if offsets_fitted and config.polish_steps else None
            R, placement, losses, polished, offsets = _polish_static(
                verts_root - centre, scene, target, M, W, area, keep, R, placement, losses, frame_losses, config,
                levels)
        best = torch.cat([torch.zeros(3, dtype=torch.float64), placement])
    order = torch.argsort(losses).tolist()
    T = scene.T_cam_root(R[None], best[None, 3:])[0].numpy()
    if not np.isfinite(T).all() or not bool(torch.isfinite(losses).all()):
        raise PipelineError("static-camera refinement failed: no finite loss (check the masks and joint readings)")
    return StaticCameraResult(
        T_cam_root=T,
        loss=float(trimmed(losses)),
        frame_losses=losses.numpy(),
        frames=tuple(chosen),
        trimmed=tuple(sorted(chosen[k] for k in order[keep:])),
        start=start,
        iterations=config.iterations,
        seconds=time.perf_counter() - t0,
        loss_before_polish=loss_before_polish,
        polish_steps=polished,
        boundary_offsets_px=offsets * fit_config.reference_side / max(target.size),
        outline=outline,
    )


_STATIC_POLISH_PATIENCE = 2  # the static polish ends after this many steps in a row without a lower loss


def _polish_static(verts_centred: torch.Tensor, scene: _Scene, target: _StageTarget, masks: torch.Tensor,
                   weights: torch.Tensor | None, area: torch.Tensor, keep: int, R: torch.Tensor,
                   placement: torch.Tensor, losses: torch.Tensor, frame_losses: Callable[..., torch.Tensor],
                   config: StaticCameraConfig,
                   levels: list[_LevelSets] | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, int, np.ndarray]:
    """Levenberg-Marquardt refinement of one pose shared by all frames (:func:`refine_static_camera`'s polish).

    The residual is the kept frames' (the ``keep`` lowest losses at the current pose) weighted mask residuals
    ``sqrt(weight_mask W / area) (S_hard - M)``; its Jacobian by central differences of the hard silhouettes, 12
    probes a unit step away, a unit moving the image by about ``polish_step_px`` (rotation about the camera axes,
    ``(a, b, log z)``), as the single-frame polish (:func:`_polish`). With ``levels`` every kept frame also has its
    own boundary offset ``delta_f`` (the mask compared is its level set ``delta_f`` working pixels inside its edge,
    one more unknown per frame, its column the level sets' central difference; within
    ``boundary_offset_max_px``), as the single-frame polish fits one: a segmenter's outline bias may differ from
    frame to frame, and a pose shared by all frames tells it from the depth. A step is taken only when it lowers
    the trimmed loss ``frame_losses`` gives (the refinement's own objective, hard-valued, at the frames' offsets);
    the steps end after ``polish_steps`` or after two in a row without a lower loss.

    Args:
        verts_centred: ``(F, V, 3)`` the frames' meshes in the root frame, less the pose's centre.
        masks, weights: ``(F, h, w)`` the working masks and the mask term's weights (or ``None``); area: ``(F,)``.
        R: ``(3, 3)``; placement: ``(3,)`` = (a, b, log z); losses: ``(F,)`` the frames' losses there.
        frame_losses: ``(R (3, 3), placement (3,), terms) -> (F,)`` losses (``terms``: the frames' ``(mask,
            distance, weight)``, ``None`` for their masks').
        levels: ``F`` frames' level sets, or ``None`` (no offsets).

    Returns:
        ``(R, placement, losses, steps taken, offsets (F,) in working pixels)``.
    """
    F = len(verts_centred)
    K = target.K
    scale = _unit_steps(K, float(verts_centred.norm(dim=2).max()), placement, config.polish_step_px)
    fit = config.fit
    delta_max = fit.boundary_offset_max_px * max(target.size) / fit.reference_side
    step_px = config.polish_step_px
    deltas = torch.zeros(F, dtype=torch.float64)

    def terms(deltas: torch.Tensor) -> tuple | None:
        """The frames' ``(mask, distance, weight)`` at ``deltas (F,)``, stacked; ``None`` without ``levels``."""
        if levels is None:
            return None
        triples = [levels[f].at(float(deltas[f])) for f in range(F)]
        weight = None if triples[0][2] is None else torch.stack([t[2] for t in triples])
        return torch.stack([t[0] for t in triples]), torch.stack([t[1] for t in triples]), weight

    def trimmed(values: torch.Tensor) -> float:
        return float(torch.sort(values).values[:keep].mean())

    eye6 = torch.eye(6, dtype=torch.float64)
    best, damping, failed, taken = trimmed(losses), 1e-3, 0, 0
    for _ in range(config.polish_steps):
        if failed >= _STATIC_POLISH_PATIENCE:
            break
        kept = torch.argsort(losses)[:keep]
        k = len(kept)
        n = 6 + (k if levels is not None else 0)  # the pose, and each kept frame's offset with ``levels``
        current = terms(deltas)
        mask_now, weight_now = (masks, weights) if current is None else (current[0], current[2])
        root = (fit.weight_mask / area).sqrt()[:, None, None].expand(masks.shape)  # (F, h, w)
        if weight_now is not None:
            root = root * weight_now.sqrt()
        probes = torch.cat([torch.zeros(1, 6, dtype=torch.float64), eye6, -eye6]) * scale  # (13, 6)
        verts = (verts_centred[kept][None] @ (rotvec_to_rotmat(probes[:, :3]) @ R)[:, None].transpose(-1, -2)
                 + _translation(placement[None] + probes[:, 3:])[:, None, None])  # (13, k, V, 3)
        silhouettes = render_hard(verts.flatten(0, 1), scene.faces, K, target.size).unflatten(0, verts.shape[:2])
        A = torch.zeros(n, n, dtype=torch.float64)
        g = torch.zeros(n, dtype=torch.float64)
        for j, f in enumerate(kept.tolist()):  # per frame: the (h * w, 6) Jacobian of one frame at a time
            r = root[f].reshape(1, -1)
            flat = silhouettes[:, j].reshape(13, -1).to(torch.float64) * r
            residual = flat[0] - mask_now[f].reshape(-1) * r[0]
            jacobian = (flat[1:7] - flat[7:]).T / 2  # (h * w, 6) per unit step
            A[:6, :6] += jacobian.T @ jacobian
            g[:6] += jacobian.T @ residual
            if levels is not None:  # S - M_delta moves with delta through the level set only
                level_step = (levels[f].at(float(deltas[f]) - step_px)[0]
                              - levels[f].at(float(deltas[f]) + step_px)[0]).reshape(-1) * r[0] / 2  # (h * w,)
                A[:6, 6 + j] = A[6 + j, :6] = jacobian.T @ level_step
                A[6 + j, 6 + j] = level_step @ level_step
                g[6 + j] = level_step @ residual
        eye = torch.eye(n, dtype=torch.float64)
        improved = False
        for factor in (1.0, 10.0, 100.0):  # Levenberg-Marquardt damping, full and half steps
            step = -torch.linalg.solve(A + damping * factor * torch.diag(torch.diag(A)) + 1e-9 * eye, g)
            for step in (step, step / 2):
                step = torch.nan_to_num(step, nan=0.0, posinf=0.0, neginf=0.0)
                pose_step = step[:6] * scale
                R_try, placement_try = rotvec_to_rotmat(pose_step[None, :3])[0] @ R, placement + pose_step[3:]
                deltas_try = deltas.clone()
                if levels is not None:
                    deltas_try[kept] = (deltas[kept] + step[6:] * step_px).clamp(-delta_max, delta_max)
                losses_try = frame_losses(R_try, placement_try, terms(deltas_try))
                if trimmed(losses_try) < best:
                    best, R, placement, losses = trimmed(losses_try), R_try, placement_try, losses_try
                    deltas = deltas_try
                    improved = True
                    break
            if improved:
                break
        taken += 1
        damping, failed = (max(damping / 3, 1e-6), 0) if improved else (damping * 10, failed + 1)
    return R, placement, losses, taken, deltas.numpy()


def _evenly(count: int, most: int) -> list[int]:
    """Indices ``0 .. count - 1``, or ``most`` of them evenly spread (first and last included)."""
    if count <= most:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, most)})


def frames_in_camera(model: ManipulatorModel, joint_angles: np.ndarray, T_cam_root: np.ndarray) -> np.ndarray:
    """Poses of every frame of ``model.frame_names`` in the camera: ``(K, 4, 4)`` ``T_cam_frame``, metres.

    Args:
        joint_angles: ``(J,)`` joint values, rad or m (as ``PoseResult.joint_angles``).
        T_cam_root: ``(4, 4)``.
    """
    q = _check_joint_angles(torch.from_numpy(np.asarray(joint_angles, dtype=np.float64)), model)
    T_root_frames = model.link_frames_in_root(q[None])[0].numpy()  # (K, 4, 4)
    return np.asarray(T_cam_root, dtype=np.float64) @ T_root_frames


def render_pose_mask(model: ManipulatorModel, result: PoseResult, camera: Camera) -> np.ndarray:
    """The fitted robot's binary silhouette (with its vertex offsets) at the camera's full resolution.

    The silhouette is that of the undistorted camera (the frame the fit works in); ``camera`` may be of any size
    with the aspect ratio of the fitted one (the overlay's image).

    Returns:
        ``(H, W)`` bool.
    """
    q = torch.from_numpy(result.joint_angles)[None]
    offsets = torch.from_numpy(result.vertex_offsets)[None]
    verts_root = model.mesh_in_root(q, offsets)[0]  # (V, 3)
    T = torch.from_numpy(np.asarray(result.T_cam_root, dtype=np.float64))
    verts_cam = verts_root @ T[:3, :3].T + T[:3, 3]
    return render_hard(verts_cam[None], model.faces, camera.K_tensor(), camera.image_size)[0].numpy()


def draw_pose_overlay(image: np.ndarray, model: ManipulatorModel, result: PoseResult, camera: Camera) -> np.ndarray:
    """The input picture undistorted, with the fitted silhouette's outline (green) and every frame of
    ``model.frame_names`` (x red, y green, z blue; axes a tenth of the robot's extent).

    Args:
        image: ``(H, W, 3)`` uint8 BGR, the camera's size (e.g. the photo, or ``viz.gray_to_bgr(mask)``).
        camera: the camera the picture came from (with its distortion).

    Returns:
        ``(H, W, 3)`` uint8 BGR, in the undistorted camera's pixels.
    """
    background, undistorted = undistort_image(image, camera)
    overlay = draw_outline(background, render_pose_mask(model, result, undistorted))
    extent = float((model.verts_link.max(0).values - model.verts_link.min(0).values).norm())
    frames = frames_in_camera(model, result.joint_angles, result.T_cam_root)
    return draw_frames(overlay, frames, undistorted.K_array(), axis_length_m=max(0.02, 0.1 * extent))


def pose_result_json(result: PoseResult, model: ManipulatorModel, camera: Camera) -> dict:
    """The result as the ``pose`` command writes it (JSON-ready: lists, floats, names).

    Keys: ``T_cam_root`` (4x4, metres), ``root``, ``tip``, ``urdf``, ``primitive``, ``loss``,
    ``loss_before_polish``, ``iterations``, ``seconds``, ``attempts``, ``retries_given_up``, ``boundary_refits``
    (``PoseResult.boundary_refits``), ``best_start``, ``starts_final_loss``, ``joints`` (name -> value used),
    ``image_size`` and ``working_size`` (``{"width", "height"}``), ``mask_dropped_fraction``,
    ``boundary_offset_px`` (``PoseResult.boundary_offset_px``), ``weight_hidden`` (the returned fit's,
    ``PoseResult.weight_hidden``), ``depth_std_m`` (``PoseResult.depth_std_m``; ``null`` for NaN), ``outline_loss``
    (``PoseResult.outline_loss``; ``null`` for NaN), ``frames_cam_m``
    (frame name -> origin in the camera frame, metres) and ``frames_px`` (frame name -> its pixel in the input
    image, lens distortion applied; ``null`` behind the camera).

    Args:
        camera: the camera the mask came from (with its distortion).
    """
    frames = frames_in_camera(model, result.joint_angles, result.T_cam_root)  # (K, 4, 4)
    origins = frames[:, :3, 3]  # (K, 3)
    pixels, _ = cv2.projectPoints(origins.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K_array(),
                                  camera.dist_array())
    pixels = pixels.reshape(-1, 2)
    H, W = result.image_size
    h, w = result.working_size
    return {
        "T_cam_root": np.asarray(result.T_cam_root).tolist(),
        "root": model.root,
        "tip": model.tip,
        "robot": model.description_path,
        "urdf": model.description_path,
        "primitive": model.primitive,
        "loss": result.loss,
        "loss_before_polish": result.loss_before_polish if math.isfinite(result.loss_before_polish) else None,
        "iterations": result.iterations,
        "seconds": result.seconds,
        "attempts": result.attempts,
        "retries_given_up": result.retries_given_up,
        "boundary_refits": result.boundary_refits,
        "best_start": result.best_start,
        "starts_final_loss": [float(v) if math.isfinite(v) else None for v in result.starts_final_loss],
        **_ambiguity_json(pose_ambiguity(result)),
        "joints": dict(zip(model.joint_names, (float(v) for v in result.joint_angles))),
        "image_size": {"width": W, "height": H},
        "working_size": {"width": w, "height": h},
        "mask_dropped_fraction": result.dropped_fraction,
        "boundary_offset_px": result.boundary_offset_px,
        "weight_hidden": result.weight_hidden,
        "depth_std_m": result.depth_std_m if math.isfinite(result.depth_std_m) else None,
        "outline_loss": result.outline_loss if math.isfinite(result.outline_loss) else None,
        "frames_cam_m": {name: origin.tolist() for name, origin in zip(model.frame_names, origins)},
        "frames_px": {name: (pixel.tolist() if origin[2] > 0 else None)
                      for name, pixel, origin in zip(model.frame_names, pixels, origins)},
    }


def _ambiguity_json(ambiguity: PoseAmbiguity) -> dict:
    """``ambiguous`` and, when some start or attempt ended far from the answer, ``runner_up``: its pose, loss, loss
    over the answer's, angle, and which start (or other attempt) it is (``null`` for the other)."""
    if ambiguity.runner_up_start < 0 and ambiguity.runner_up_attempt < 0:
        return {"ambiguous": False, "runner_up": None}
    return {
        "ambiguous": ambiguity.ambiguous,
        "runner_up": {
            "T_cam_root": ambiguity.runner_up_T_cam_root.tolist(),
            "loss": ambiguity.runner_up_loss,
            "loss_ratio": ambiguity.runner_up_loss_ratio if math.isfinite(ambiguity.runner_up_loss_ratio) else None,
            "rotation_deg": ambiguity.rotation_deg,
            "start": ambiguity.runner_up_start if ambiguity.runner_up_start >= 0 else None,
            "attempt": ambiguity.runner_up_attempt if ambiguity.runner_up_attempt >= 0 else None,
        },
    }


# ---------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _Scene:
    """The robot at the given joint values: what the loss needs per iteration, precomputed once."""

    verts_root: torch.Tensor  # (V, 3) mesh without offsets in the root frame
    R_root_vert: torch.Tensor  # (V, 3, 3) rotation of each vertex's link in the root frame (offsets -> root)
    faces: torch.Tensor  # (F, 3)
    cull: bool  # cull back faces of the full mesh
    closed: bool  # the full mesh is closed and consistently wound: culling leaves its hard silhouette as it is
    hull_verts_root: torch.Tensor  # (Vh, 3) per-link convex hulls, root frame
    hull_faces: torch.Tensor  # (Fh, 3)
    centre: torch.Tensor  # (3,) centre of the bounding box, root frame
    offset_norm: float  # 1 / (V * offset_scale^2)

    @staticmethod
    def build(model: ManipulatorModel, q: torch.Tensor, config: PoseFitConfig) -> "_Scene":
        T_root_link = model.link_poses(q[None])[0]  # (L, 4, 4)
        verts_root = model.mesh_in_root(q[None])[0]
        links = _link_geometry(model, config.hull_points)
        cull = config.cull_back_faces and links.closed
        if config.cull_back_faces and not cull:
            logger.info("the mesh is not closed and consistently wound: back faces are drawn too")
        T_hull = T_root_link[links.hull_link_index]  # (Vh, 4, 4)
        hull_verts = (T_hull[:, :3, :3] @ links.hull_verts_link.to(q)[:, :, None])[:, :, 0] + T_hull[:, :3, 3]
        return _Scene(
            verts_root=verts_root,
            R_root_vert=T_root_link[model.vert_link_index, :3, :3],
            faces=model.faces,
            cull=cull,
            closed=links.closed,
            hull_verts_root=hull_verts,
            hull_faces=links.hull_faces.to(q.device),
            centre=(verts_root.min(0).values + verts_root.max(0).values) / 2,
            offset_norm=1.0 / (verts_root.shape[0] * config.offset_scale_m ** 2),
        )

    def verts_cam(self, R: torch.Tensor, placement: torch.Tensor, *, hull: bool,
                  offsets: torch.Tensor | None = None) -> torch.Tensor:
        """Camera-frame vertices for rotations ``R (S, 3, 3)`` and ``placement (S, 3)`` = (a, b, log z): of the
        link hulls, ``(S, Vh, 3)``, or of the link meshes moved by ``offsets (S, V, 3)`` (link frames; ``None``
        for none), ``(S, V, 3)``."""
        if hull:
            verts = self.hull_verts_root[None]  # (1, Vh, 3)
        elif offsets is None:
            verts = self.verts_root[None]  # (1, V, 3)
        else:
            verts = self.verts_root + torch.einsum("vij,svj->svi", self.R_root_vert, offsets)  # (S, V, 3)
        return (verts - self.centre) @ R.transpose(-1, -2) + _translation(placement)[:, None]

    def T_cam_root(self, R: torch.Tensor, placement: torch.Tensor) -> torch.Tensor:
        """``(S, 4, 4)``: ``v_cam = R (v - c) + t`` as a transform of root-frame points."""
        return Rt_to_matrix4x4(R, (_translation(placement) - R @ self.centre)[:, :, None]).detach()


@dataclass(frozen=True, eq=False)
class _StageTarget:
    """The mask at one stage's resolution and what the losses need of it."""

    size: tuple[int, int]  # (H, W)
    K: torch.Tensor  # (3, 3)
    mask: torch.Tensor  # (H, W) float64 0/1 (with coverage_target: each pixel's share of the mask)
    distance: torch.Tensor  # (H, W) D, already divided by gamma and scaled to the reference side
    weight: torch.Tensor | None  # (H, W) of the mask term (and already in D), or None for all ones
    area: float  # pixels
    settings: SoftRasterSettings
    straight_through: bool

    @staticmethod
    def build(mask: np.ndarray, camera: Camera, full: tuple[int, int], stage: PoseStage, config: PoseFitConfig
              ) -> "_StageTarget":
        size = working_size(camera.image_size, max(1, round(max(full) * stage.scale)))
        if size == mask.shape:
            small = coverage = mask
        else:  # the coverage once, for the thresholded mask and (coverage_target) the mask term's target
            coverage = _mask_coverage(mask, size)
            small = _half_covered(coverage)
        M = torch.from_numpy(coverage if config.coverage_target else small).to(torch.float64)
        D, W = _distance_term(small, config)
        return _StageTarget(
            size=size,
            K=resize_camera(camera, size).K_tensor(),
            mask=M,
            distance=D,
            weight=W,
            area=float(M.sum()),
            settings=SoftRasterSettings.from_sigma(stage.sigma_px2, eps=config.cutoff_eps, saturation=(
                SoftRasterSettings.saturation if stage.hull or config.saturation is None else config.saturation)),
            straight_through=stage.straight_through,
        )


def _total_loss(scene: _Scene, target: _StageTarget, R_ref: torch.Tensor, pose: torch.Tensor, hull: bool,
                offsets: torch.Tensor | None, config: PoseFitConfig) -> torch.Tensor:
    """``(S,)`` loss of each start (module docstring) for ``pose (S, 6)`` about ``R_ref (S, 3, 3)``, rendering the
    link hulls or the link meshes with ``offsets (S, V, 3)`` (``None``: fixed at zero)."""
    R = rotvec_to_rotmat(pose[:, :3]) @ R_ref  # (S, 3, 3)
    verts = scene.verts_cam(R, pose[:, 3:], hull=hull, offsets=offsets)  # (S, V, 3)
    silhouette = _render(verts, scene, target, hull=hull)  # (S, H, W)
    loss = config.weight_mask * mask_loss(silhouette, target.mask, target.weight) / target.area
    if config.weight_distance:
        loss = loss + config.weight_distance * distance_loss(silhouette, target.distance) / target.area
    if config.weight_appearance:
        loss = loss + config.weight_appearance * appearance_loss(silhouette, target.mask) / target.area
    if offsets is not None and config.weight_offset:
        loss = loss + config.weight_offset * scene.offset_norm * (offsets * offsets).sum(dim=(1, 2))
    return loss


def _render(verts_cam: torch.Tensor, scene: _Scene, target: _StageTarget, hull: bool) -> torch.Tensor:
    """Soft silhouettes ``(S, H, W)`` of ``verts_cam (S, V, 3)`` (back faces culled per start where allowed);
    with ``target.straight_through`` the value is the hard silhouette's."""
    S, V, _ = verts_cam.shape
    faces = scene.hull_faces if hull else scene.faces
    # faces turned away (normal . corner > 0, camera frame) skipped in the rasterizer's face set-up
    settings = dataclasses.replace(target.settings, cull_back_faces=hull or scene.cull)
    if target.straight_through and not torch.is_grad_enabled():
        # no gradient wanted: the value alone, the hard silhouette, drawn without the soft pass (a loss of every
        # start at the working resolution took 0.28 s of a Baxter fit's 7 s soft). ``s + (h - s)`` is exactly
        # ``h`` in floating point for s in [0, 1], h in {0, 1}, so this is the value of the branch below, bit for bit
        return render_hard(verts_cam, faces, target.K, target.size, settings).to(verts_cam.dtype)
    packed = (faces[None] + (torch.arange(S) * V)[:, None, None]).reshape(-1, 3)
    verts_batch = torch.arange(S).repeat_interleave(V)  # (S * V,)
    if not target.straight_through:
        return render_silhouette_packed(verts_cam.reshape(S * V, 3), packed, verts_batch, target.K, S, target.size,
                                        settings)
    # the value of the hard silhouette of the drawn faces (the front faces of a closed mesh cover its whole
    # silhouette), the gradient of the soft one, from one pass
    return render_silhouette_packed(verts_cam.reshape(S * V, 3), packed, verts_batch, target.K, S, target.size,
                                    settings, straight_through=True)


def _initial_starts(scene: _Scene, target: _StageTarget, config: PoseFitConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``starts`` best of ``candidates`` random rotations, each placed on the mask by moment matching.

    Returns:
        ``(R_ref (S, 3, 3), placement (S, 3))``, best first.
    """
    generator = torch.Generator().manual_seed(config.seed)
    N = config.candidates
    quaternion = torch.randn(N, 4, generator=generator, dtype=torch.float64)
    R = quaternion_to_rotation_matrix(quaternion)  # (N, 3, 3) uniform; kornia normalises (w, x, y, z)
    H, W = target.size
    K = target.K
    focal = torch.stack([K[0, 0], K[1, 1]])
    centre_px = torch.stack([K[0, 2], K[1, 2]])
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    mask_uv = torch.stack([(u * target.mask).sum(), (v * target.mask).sum()]) / target.area  # (2,) centroid
    radius = float((scene.hull_verts_root - scene.centre).norm(dim=1).max())  # robot radius about its centre, m
    depth = 2.0 * radius * float(focal.max()) / math.sqrt(target.area)  # a first guess, refined by the moments
    first = torch.cat([(mask_uv - centre_px) / focal, torch.tensor([math.log(depth)], dtype=torch.float64)])

    def placed(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Moment matching of rotations ``R (n, 3, 3)``: ``(placement (n, 3), IoU with the mask (n,))``."""
        placement = first.repeat(len(R), 1)  # (n, 3)
        for _ in range(2):  # scale the depth by the area ratio, shift the centroid onto the mask's
            hard = render_hard(scene.verts_cam(R, placement, hull=True), scene.hull_faces, K, (H, W)).to(torch.float64)
            area = hard.sum(dim=(1, 2))  # (n,)
            seen = area > 0
            centroid = torch.stack([(hard * u).sum(dim=(1, 2)), (hard * v).sum(dim=(1, 2))], 1) / area.clamp_min(1)[:, None]
            placement[:, 2] += torch.where(seen, 0.5 * torch.log(area.clamp_min(1) / target.area), 0.0)
            placement[:, :2] += torch.where(seen[:, None], (mask_uv - centroid) / focal, 0.0)
        hard = render_hard(scene.verts_cam(R, placement, hull=True), scene.hull_faces, K, (H, W)).to(torch.float64)
        intersection = (hard * target.mask).sum(dim=(1, 2))
        return placement, intersection / (hard.sum(dim=(1, 2)) + target.area - intersection)

    placement, iou = placed(R)
    if config.flip_candidates > 0:
        top = torch.argsort(iou, descending=True)[: config.flip_candidates]
        flips = _flip_rotations(target.mask, u, v, mask_uv, target.area)  # (3, 3, 3)
        R_flipped = (flips[:, None] @ R[top][None]).reshape(-1, 3, 3)  # (3 F, 3, 3), turned about camera axes
        placement_flipped, iou_flipped = placed(R_flipped)
        R = torch.cat([R, R_flipped])
        placement, iou = torch.cat([placement, placement_flipped]), torch.cat([iou, iou_flipped])
    best = _distinct(R, torch.argsort(iou, descending=True), config.starts, config.min_start_separation_deg)
    return R[best].clone(), placement[best].clone()


def _kept_starts(R: torch.Tensor, loss: torch.Tensor, keep: int, separation_deg: float) -> torch.Tensor:
    """Indices ``(keep,)`` of the starts (rotations ``R (N, 3, 3)``, losses ``(N,)``, ``keep <= N``) that enter
    the next stage: the lowest loss first, skipping starts within ``separation_deg`` of one already kept (one per
    basin; 0: simply the ``keep`` lowest), then, if fewer basins than ``keep`` were found, the next lowest."""
    order = torch.argsort(loss)
    chosen = _distinct(R, order, keep, separation_deg)
    rest = order[~torch.isin(order, chosen)]
    return torch.cat([chosen, rest[: keep - len(chosen)]])


def _distinct(R: torch.Tensor, order: torch.Tensor, count: int, separation_deg: float) -> torch.Tensor:
    """Indices ``(<= count,)`` of rotations ``R (N, 3, 3)`` taken in ``order`` (best first), skipping any within
    ``separation_deg`` of one already taken (0: the first ``count`` of ``order``)."""
    chosen: list[int] = []
    cos_separation = math.cos(math.radians(separation_deg))
    for n in order.tolist():
        if len(chosen) == count:
            break
        if chosen and separation_deg > 0:
            trace = torch.einsum("kij,ij->k", R[chosen], R[n])  # trace(R_k^T R_n) = 1 + 2 cos(angle)
            if bool(((trace - 1) / 2 > cos_separation).any()):
                continue
        chosen.append(n)
    return torch.tensor(chosen, dtype=torch.long)


def _placement_of(scene: "_Scene", T_cam_root: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The inverse of ``scene.T_cam_root``: ``(R (1, 3, 3), placement (1, 3) = (a, b, log z))`` of a pose whose
    mesh centre ``t = R c + t_T`` lies in front of the camera.

    Raises:
        ShapeError: the robot's centre is not in front of the camera (z <= 0).
    """
    T = torch.from_numpy(np.asarray(T_cam_root, dtype=np.float64))
    R = T[:3, :3]
    centre = R @ scene.centre + T[:3, 3]  # (3,) the mesh centre in the camera frame
    if not float(centre[2]) > 0.0:
        raise ShapeError(f"initial_T_cam_root: the robot's centre is not in front of the camera (z = {float(centre[2]):.3g} m)")
    placement = torch.stack([centre[0] / centre[2], centre[1] / centre[2], torch.log(centre[2])])
    return R[None].clone(), placement[None]


def _flip_rotations(mask: torch.Tensor, u: torch.Tensor, v: torch.Tensor, mask_uv: torch.Tensor, area: torch.Tensor
                    ) -> torch.Tensor:
    """``(3, 3, 3)`` rotations by 180 degrees about the mask's two principal axes in the image plane (as camera-frame
    directions ``(e_u, e_v, 0)``) and about the optical axis: ``F = 2 a a^T - I`` for each unit axis ``a``."""
    du, dv = u - mask_uv[0], v - mask_uv[1]  # (H, W)
    cov = torch.stack([(mask * du * du).sum(), (mask * du * dv).sum(), (mask * dv * du).sum(), (mask * dv * dv).sum()])
    _, vectors = torch.linalg.eigh((cov / area).reshape(2, 2))  # columns: principal directions
    axes = torch.zeros(3, 3, dtype=torch.float64)
    axes[0, :2], axes[1, :2], axes[2, 2] = vectors[:, 0], vectors[:, 1], 1.0
    return 2.0 * axes[:, :, None] * axes[:, None, :] - torch.eye(3, dtype=torch.float64)


def _unit_steps(K: torch.Tensor, radius_m: float, placement: torch.Tensor, step_px: float) -> torch.Tensor:
    """``(6,)`` pose steps (rotation about the camera axes, ``(a, b, log z)``) that each move the image of a robot of
    ``radius_m`` at ``placement`` by about ``step_px`` pixels (the polishes' finite-difference unit)."""
    radius_px = max(float(K[0, 0]), float(K[1, 1])) * radius_m / float(torch.exp(placement[2]))
    per_px = 1.0 / max(radius_px, 1.0)  # rad or log depth per pixel of image motion at the robot's rim
    return step_px * torch.tensor([per_px, per_px, per_px, 1 / float(K[0, 0]), 1 / float(K[1, 1]), per_px],
                                  dtype=torch.float64)


def _polish(scene: _Scene, target: _StageTarget, R: torch.Tensor, placement: torch.Tensor,
            offsets: torch.Tensor | None, config: PoseFitConfig, levels: _LevelSets | None = None,
            delta_px: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, float, float]:
    """Refinement of one pose on the last stage's loss without its soft gradient (module docstring, Polish).

    Steps are in pose units scaled so that a unit step moves the image by about ``polish_step_px`` (rotation
    about the camera axes and ``(a, b, log z)``). First ``polish_newton_steps`` Levenberg-Marquardt steps on the
    mask residual ``S_hard - M``, its Jacobian by central differences of the hard silhouette (12 probes one unit
    away); then a (1 + lambda) random search: ``polish_rounds`` rounds of ``polish_samples`` Gaussian steps,
    shrunk after a round without a lower loss. A step is taken only when it lowers the loss, ``_total_loss``'s
    value with the hard silhouette, evaluated in a window around the mask and the silhouette.

    With ``levels`` (``PoseFitConfig.polish_boundary_offset``) the boundary offset ``delta`` is a seventh unknown:
    the loss compares the silhouette with the mask's level set ``delta`` inside its edge (``levels.at``), the
    Jacobian's seventh column is the level sets' central difference one pixel either side, and the random steps
    move it too; it stays within ``boundary_offset_max_px``. Fitted beside the pose, the offset is told from the
    depth by the links' lengths as well as their widths (a dilation widens every outline by the same pixels, a
    nearer robot scales it).

    Args:
        R: ``(3, 3)`` rotation; placement: ``(3,)`` = (a, b, log z); offsets: ``(V, 3)`` or ``None``.
        levels: the working mask's level sets, or ``None`` (``target``'s mask, the offset not fitted).
        delta_px: the offset to start from, working pixels (``levels`` only).

    Returns:
        ``(R (3, 3), placement (3,), loss, delta_px, log_depth_std)``: the best pose found (the given one if
        nothing was lower), its offset (working pixels; ``delta_px`` itself without ``levels``) and the standard
        deviation of its log depth (:func:`_log_depth_std`, at the pose found; NaN if it cannot be linearised).
    """
    hull = config.stages[-1].hull
    generator = torch.Generator().manual_seed(config.seed)
    K = target.K
    radius_m = float(((scene.hull_verts_root if hull else scene.verts_root) - scene.centre).norm(dim=1).max())
    scale = _unit_steps(K, radius_m, placement, config.polish_step_px)
    n = 6 if levels is None else 7  # unknowns: the pose, and the boundary offset with ``levels``
    if levels is not None:
        scale = torch.cat([scale, scale.new_tensor([config.polish_step_px])])
    delta_max = config.boundary_offset_max_px * max(target.size) / config.reference_side
    offsets = None if offsets is None else offsets[None]
    window = _PolishWindow(target, config, levels)
    best, silhouette = window.loss(scene, R[None], placement[None], hull, offsets, torch.tensor([delta_px]))
    best = float(best[0])
    window.fit_to(silhouette[0])

    def perturbed(steps: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:  # (N, n), ``scale`` units
        steps = steps * scale
        deltas = (delta_px + steps[:, 6]).clamp(-delta_max, delta_max) if n == 7 else torch.full_like(
            steps[:, 0], delta_px)  # (N,)
        return rotvec_to_rotmat(steps[:, :3]) @ R, placement + steps[:, 3:6], deltas  # (N, 3, 3), (N, 3), (N,)

    eye = torch.eye(n, dtype=torch.float64)

    def linearised() -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(residual (P,), jacobian (P, n))`` of the (weighted) mask residual ``S_hard - M`` at the current pose,
        per unit step (``scale``), by central differences; ``None`` when a probe reached the window's edge (the
        window is then refitted)."""
        R_try, placement_try, _ = perturbed(torch.cat([torch.zeros(1, n, dtype=torch.float64), eye[:6], -eye[:6]]))
        loss, silhouette = window.loss(scene, R_try, placement_try, hull, offsets, torch.full((13,), delta_px))
        if not bool(torch.isfinite(loss).all()):  # a probe reached the window's edge
            window.fit_to(silhouette[0])
            return None
        flat = silhouette.reshape(13, -1).to(torch.float64)  # (13, P)
        residual = flat[0] - window.mask(delta_px).reshape(-1)  # (P,)
        jacobian = (flat[1:7] - flat[7:]).T / 2  # (P, 6) per unit step, central differences
        if n == 7:  # the residual S - M_delta moves with delta through the level set only
            step_px = float(scale[6])
            level_step = window.mask(delta_px - step_px) - window.mask(delta_px + step_px)  # (h, w)
            jacobian = torch.cat([jacobian, level_step.reshape(-1, 1) / 2], 1)  # (P, 7)
        root = window.root_weight(delta_px)
        if root is not None:  # the weighted least squares of the mask term
            residual, jacobian = residual * root.reshape(-1), jacobian * root.reshape(-1, 1)
        return residual, jacobian

    damping = 1e-3
    failed = 0  # Levenberg-Marquardt steps in a row without a lower loss
    for _ in range(config.polish_newton_steps):  # Gauss-Newton on the mask residual, Jacobian by differences
        if config.polish_newton_patience and failed >= config.polish_newton_patience:
            break
        linear = linearised()
        if linear is None:
            continue
        residual, jacobian = linear
        A, g = jacobian.T @ jacobian, jacobian.T @ residual
        steps = []
        for factor in (1.0, 10.0, 100.0):  # Levenberg-Marquardt damping, full and half steps
            step = -torch.linalg.solve(A + damping * factor * torch.diag(torch.diag(A)) + 1e-9 * eye, g)
            steps += [step, step / 2]
        R_try, placement_try, delta_try = perturbed(torch.nan_to_num(torch.stack(steps), nan=0.0, posinf=0.0,
                                                                     neginf=0.0))
        loss, silhouette = window.loss(scene, R_try, placement_try, hull, offsets, delta_try)
        i = int(torch.argmin(loss))
        if float(loss[i]) < best:
            best, R, placement, delta_px = float(loss[i]), R_try[i], placement_try[i], float(delta_try[i])
            window.fit_to(silhouette[i])
            damping = max(damping / 3, 1e-6)
            failed = 0
        else:
            damping *= 10
            failed += 1
    shrink = 1.0  # the random steps' scale relative to polish_step_px
    for _ in range(config.polish_rounds):  # random search
        if config.polish_step_px * shrink < config.polish_min_step_px:
            break
        R_try, placement_try, delta_try = perturbed(torch.randn(config.polish_samples, n, generator=generator,
                                                                dtype=torch.float64))
        loss, silhouette = window.loss(scene, R_try, placement_try, hull, offsets, delta_try)
        i = int(torch.argmin(loss))
        if float(loss[i]) < best:
            best, R, placement, delta_px = float(loss[i]), R_try[i], placement_try[i], float(delta_try[i])
            window.fit_to(silhouette[i])
        else:
            scale = scale * _POLISH_SHRINK
            shrink *= _POLISH_SHRINK
    scale = scale / shrink  # the probes' unit again
    linear = linearised() or linearised()  # once more after a refitted window
    y0, y1, x0, x1 = window.box  # the residual's window (it changes only when a probe reached its edge)
    log_depth_std = math.nan if linear is None else _log_depth_std(*linear, float(scale[5]), (y1 - y0, x1 - x0))
    return R, placement, best, delta_px, log_depth_std


def _polished(scene: _Scene, mask: np.ndarray, camera: Camera, R: torch.Tensor, placement: torch.Tensor,
              offsets: torch.Tensor | None, config: PoseFitConfig, *, estimate_from: torch.Tensor | None,
              boundary_px: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, float, float, float]:
    """:func:`_polish` of the pose ``(R (3, 3), placement (3,))`` with ``offsets (V, 3)`` (``None``: none) on the
    last stage's loss against the (undistorted) ``mask``'s level set ``boundary_px`` (reference pixels) inside its
    edge; with ``estimate_from`` (the vertex offsets ``(V, 3)`` to draw the silhouette with) that offset is first
    estimated from link widths at the pose (``_boundary_offset``); with ``config.polish_boundary_offset`` the polish
    fits it beside the pose (a seventh unknown, from that estimate).

    Returns:
        ``(R, placement, loss, boundary_px, depth_std_m)``: the polished pose, its loss (the polish's windowed
        loss), the boundary offset (reference pixels) and the depth's standard deviation (metres).
    """
    if estimate_from is not None:  # again, from the pose given (a fit's estimates before came from link hulls)
        boundary_px = _boundary_offset(mask, _silhouette_of(scene, R, placement, estimate_from, camera), config)
    fitted = _mask_level_set(mask, boundary_px * max(mask.shape) / config.reference_side)
    target = _StageTarget.build(fitted, camera, working_size(camera.image_size, config.working_max_side),
                                config.stages[-1], config)
    # the offset a seventh unknown of the polish, from this estimate
    levels = _LevelSets(_resize_mask(mask, target.size), config) if config.polish_boundary_offset else None
    per_ref = max(target.size) / config.reference_side  # working pixels per reference pixel
    R, placement, loss, delta, log_depth_std = _polish(scene, target, R, placement, offsets, config, levels,
                                                      boundary_px * per_ref)
    if levels is not None and delta != boundary_px * per_ref:
        boundary_px = delta / per_ref
    return R, placement, loss, boundary_px, DEPTH_STD_SCALE * log_depth_std * float(torch.exp(placement[2]))


def _log_depth_std(residual: torch.Tensor, jacobian: torch.Tensor, log_depth_per_unit: float,
                   shape: tuple[int, int]) -> float:
    """The standard deviation of the log depth at a fitted pose, from the linearised mask residual: ``residual (P,)``
    (the window's ``shape (h, w)``, row-major) and its ``jacobian (P, n)`` per unit step (:func:`_polish`'s; column 5
    moves the log depth by ``log_depth_per_unit``).

    Gauss-Newton covariance ``s^2 (J^T J)^-1``, the other unknowns (rotation, image position, the boundary offset
    where fitted) free, so a depth that trades against them shows as uncertain; ``s^2`` the residual's mean
    square over the pixels the pose or the mask touch (a non-zero residual or Jacobian row), less the unknowns, at
    least one mismatched pixel's worth. A mask's errors are not independent pixels: an outline drawn too wide, a
    missing part, a blob are runs of mismatched pixels that move together, so the variance is multiplied by the
    mismatched pixels per connected run (8-connected) of the mismatch, the residual's effective number of pixels
    per independent error. NaN where no pixel moves with the depth or the Jacobian is singular."""
    n = jacobian.shape[1]
    if not bool((jacobian[:, 5] != 0).any()):  # no pixel moves with the depth: nothing to say
        return math.nan
    mismatch = residual != 0
    touched = int((mismatch | (jacobian != 0).any(dim=1)).sum())
    if touched <= n:
        return math.nan
    s2 = max(float(residual @ residual), 1.0) / (touched - n)
    runs = cv2.connectedComponents(mismatch.reshape(shape).cpu().numpy().astype(np.uint8), connectivity=8)[0] - 1
    pixels_per_run = int(mismatch.sum()) / runs if runs > 0 else 1.0
    A = jacobian.T @ jacobian
    try:
        variance = float(torch.linalg.inv(A + 1e-12 * torch.eye(n, dtype=A.dtype) * A.diagonal().max())[5, 5])
    except RuntimeError:  # singular
        return math.nan
    if not (math.isfinite(variance) and variance >= 0.0):
        return math.nan
    return math.sqrt(s2 * pixels_per_run * variance) * log_depth_per_unit


_POLISH_SHRINK = 0.85  # step factor after a round without a lower loss
# PoseResult.depth_std_m over the linearised estimate (_log_depth_std): the mask's errors are biases more than noise
# (an outline drawn too wide, a hidden part), which the linearisation does not see. Chosen on the tuning views of
# benchmarks/acceptance_robots.py (Panda, UR5, Baxter, 6000-6009, clean and noisy masks, CAD and the default
# geometry, 640x480: 120 fits) as half the 95th percentile of |end-effector depth error| / linearised std, so that
# 95 % of those errors lie within 2 standard deviations (docs/any-manipulator.md).
DEPTH_STD_SCALE = 13.0


class _PolishWindow:
    """The last stage's loss evaluated on a window of its image: the mask's bounding box and the current
    silhouette's, widened by a margin; a pose whose silhouette reaches the window's edge (inside the image) counts
    as +inf, so the windowed loss equals the whole image's wherever it is finite."""

    def __init__(self, target: _StageTarget, config: PoseFitConfig, levels: _LevelSets | None = None) -> None:
        self.target, self.config, self.levels = target, config, levels
        rows = torch.nonzero(target.mask.any(dim=1)).flatten()
        cols = torch.nonzero(target.mask.any(dim=0)).flatten()
        self.mask_box = (int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1)
        self.margin = 8 + math.ceil(6 * config.polish_step_px)
        self.box = (0, target.size[0], 0, target.size[1])  # the whole image until fit_to

    def fit_to(self, silhouette: torch.Tensor) -> None:
        """Re-centre the window on the mask and ``silhouette`` (``(h, w)`` bool in the current window)."""
        y0, y1, x0, x1 = self.mask_box
        rows = torch.nonzero(silhouette.any(dim=1)).flatten()
        cols = torch.nonzero(silhouette.any(dim=0)).flatten()
        if rows.numel():
            y0, y1 = min(y0, self.box[0] + int(rows[0])), max(y1, self.box[0] + int(rows[-1]) + 1)
            x0, x1 = min(x0, self.box[2] + int(cols[0])), max(x1, self.box[2] + int(cols[-1]) + 1)
        H, W = self.target.size
        m = self.margin
        self.box = (max(0, y0 - m), min(H, y1 + m), max(0, x0 - m), min(W, x1 + m))

    def terms(self, delta_px: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(mask, distance, weight)`` of the whole working image, as ``_LevelSets.at``: the target's, or with
        ``levels`` its level set ``delta_px`` working pixels inside its edge."""
        if self.levels is None:
            return self.target.mask, self.target.distance, self.target.weight
        return self.levels.at(delta_px)

    def mask(self, delta_px: float) -> torch.Tensor:
        """``(h, w)`` float64 in [0, 1] (0/1 unless ``coverage_target``): the target's mask in the window (its
        level set ``delta_px`` working pixels inside its edge with ``levels``)."""
        y0, y1, x0, x1 = self.box
        return self.terms(delta_px)[0][y0:y1, x0:x1]

    def root_weight(self, delta_px: float) -> torch.Tensor | None:
        """``(h, w)``: the square root of the mask term's weights in the window (``None`` for ones)."""
        y0, y1, x0, x1 = self.box
        weight = self.terms(delta_px)[2]
        return None if weight is None else weight[y0:y1, x0:x1].sqrt()

    def loss(self, scene: _Scene, R: torch.Tensor, placement: torch.Tensor, hull: bool,
             offsets: torch.Tensor | None, deltas: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``(N,)`` losses of the poses ``R (N, 3, 3)``, ``placement (N, 3)`` against the mask's level sets
        ``deltas (N,)`` (working pixels; ``None``: 0; ignored without ``levels``) and their silhouettes
        ``(N, h, w)`` bool in the window. Normalised by the target's area whatever the level set's, so that
        offsets compare."""
        y0, y1, x0, x1 = self.box
        target, config = self.target, self.config
        K = target.K.clone()
        K[0, 2] -= x0
        K[1, 2] -= y0
        verts = scene.verts_cam(R, placement, hull=hull, offsets=offsets)
        faces = scene.hull_faces if hull else scene.faces
        # (N, h, w) bool; the back faces of a closed mesh (the link hulls always) lie behind its front faces, which
        # cover its silhouette: culled, the same pixels at about half the faces
        silhouette = render_hard(verts, faces, K, (y1 - y0, x1 - x0),
                                 SoftRasterSettings(cull_back_faces=hull or scene.closed))
        if self.levels is None:  # (h, w) each
            mask, distance, weight = (None if t is None else t[y0:y1, x0:x1] for t in self.terms(0.0))
        else:  # (N, h, w) each
            deltas = torch.zeros(len(R)) if deltas is None else deltas
            triples = [self.terms(float(d)) for d in deltas]  # cached: candidates share level sets
            mask, distance = (torch.stack([t[k][y0:y1, x0:x1] for t in triples]) for k in (0, 1))
            weight = None if triples[0][2] is None else torch.stack([t[2][y0:y1, x0:x1] for t in triples])
        area = silhouette.sum(dim=(1, 2)).to(torch.float64)
        wrong = (silhouette.to(torch.float64) - mask) ** 2  # silhouette XOR mask, or a coverage target's share
        wrong = wrong.sum(dim=(1, 2)) if weight is None else (wrong * weight).sum(dim=(1, 2))
        loss = config.weight_mask * wrong
        if config.weight_distance:
            loss = loss + config.weight_distance * (silhouette * distance).sum(dim=(1, 2))
        if config.weight_appearance:
            loss = loss + config.weight_appearance * appearance_loss(area[:, None, None], torch.full_like(
                area[:, None, None], target.area))
        loss = loss / target.area
        if offsets is not None and config.weight_offset:
            loss = loss + config.weight_offset * scene.offset_norm * (offsets * offsets).sum(dim=(1, 2))
        H, W = target.size
        edges = []  # window edges inside the image: a silhouette there may go on outside the window
        if y0 > 0:
            edges.append(silhouette[:, 0, :].any(dim=1))
        if y1 < H:
            edges.append(silhouette[:, -1, :].any(dim=1))
        if x0 > 0:
            edges.append(silhouette[:, :, 0].any(dim=1))
        if x1 < W:
            edges.append(silhouette[:, :, -1].any(dim=1))
        if edges:
            loss = torch.where(torch.stack(edges).any(dim=0), math.inf, loss)
        return torch.where(torch.isfinite(loss), loss, math.inf), silhouette


def _silhouette_of(scene: _Scene, R: torch.Tensor, placement: torch.Tensor, offsets: torch.Tensor, camera: Camera,
                   *, cull: bool = False) -> np.ndarray:
    """``(H, W)`` bool: the hard silhouette of the link meshes at the pose ``(R (3, 3), placement (3,))`` with
    ``offsets (V, 3)``, through ``camera``; every face drawn, or with ``cull`` only those facing the camera."""
    with torch.no_grad():
        verts = scene.verts_cam(R[None], placement[None], hull=False, offsets=offsets[None])
        return render_hard(verts, scene.faces, camera.K_tensor(), camera.image_size,
                           SoftRasterSettings(cull_back_faces=cull))[0].numpy()


def _cull_if_unseen(scene: _Scene, R: torch.Tensor, placement: torch.Tensor, offsets: torch.Tensor, camera: Camera,
                    silhouette: np.ndarray, tolerance: float) -> _Scene:
    """``scene`` with its back faces culled (``cull=True``) when, at the pose ``(R (3, 3), placement (3,))`` with
    ``offsets (V, 3)`` through ``camera``, culling takes at most ``tolerance`` of the mesh's hard ``silhouette``
    (``(H, W)`` bool, every face drawn: ``_silhouette_of`` at that pose) away (``PoseFitConfig.cull_open_tolerance``);
    ``scene`` itself otherwise. For a mesh that is not closed: most of a CAD mesh's back faces lie behind its front
    faces, and those that show through a hole are what this measures."""
    area = int(silhouette.sum())
    lost = int((silhouette & ~_silhouette_of(scene, R, placement, offsets, camera, cull=True)).sum())
    culled = area > 0 and lost <= tolerance * area
    logger.info("mesh not closed: culling its back faces takes %d of its %d silhouette pixels away at the pose "
                "reached; %s", lost, area, "culled" if culled else "all faces drawn")
    return dataclasses.replace(scene, cull=True) if culled else scene


def _explained_mask(mask: np.ndarray, silhouette: np.ndarray, config: PoseFitConfig) -> np.ndarray:
    """``mask (H, W)`` without the connected components that ``silhouette (H, W)`` does not come near
    (``PoseFitConfig.drop_unexplained``)."""
    count, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    if count <= 2 or not silhouette.any():
        return mask
    radius = max(1, round(config.unexplained_margin_px * max(mask.shape) / config.reference_side))
    near = cv2.dilate(silhouette.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE,
                                                                              (2 * radius + 1, 2 * radius + 1)))
    touched = np.unique(labels[(near > 0) & mask])
    kept = np.isin(labels, touched[touched > 0])
    if kept.sum() < 0.5 * mask.sum():
        return mask
    if kept.sum() < mask.sum():
        logger.info("dropped %d mask pixels in components the fit does not explain", int(mask.sum() - kept.sum()))
    return kept


def _boundary_offset(mask: np.ndarray, silhouette: np.ndarray, config: PoseFitConfig) -> float:
    """How far the edge of ``mask (H, W)`` lies outside that of ``silhouette (H, W)`` (reference pixels; 0 below
    ``boundary_offset_min_px`` or above ``boundary_offset_max_px``, or without a skeleton pixel inside the mask).

    At the silhouette's skeleton pixels inside the mask, the pairs (the silhouette's inner distance ``x``, the
    mask's ``y``), each the largest within ``boundary_search_px`` (so that a silhouette a little off the mask still
    compares link widths): a dilation of the mask by ``delta`` adds ``delta`` to ``y``, a depth error by a factor
    ``s`` scales ``x`` by ``s``. So ``y = delta + x / s``: ``delta`` is the intercept of a line through the pairs
    (least squares, three rounds dropping pairs more than 1-1.5 px off it), or the median of ``y - x`` when the
    widths do not spread over a pixel. Separating the depth keeps the estimate from feeding on the fit's own depth
    error (a pose too far away draws thinner links, which would look like a wider mask); it can only do so where
    the links' widths differ (a toy arm of links of one width: 1.7 to 3.3 px for a 3 % depth error either way)."""
    if not silhouette.any() or mask.all() or silhouette.all():
        return 0.0
    radius = max(1, round(config.boundary_search_px * max(mask.shape) / config.reference_side))
    # On the box of both grown by a pixel, the skeleton and the inner distances are those of the whole image (both
    # are 0 outside it, and dilating takes the largest), at a fraction of a large image's time.
    window = foreground_window(mask | silhouette, 1)
    full_side, mask, silhouette = max(mask.shape), mask[window], silhouette[window]
    skeleton = skeletonize(silhouette) & mask
    if not skeleton.any():
        return 0.0
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    inner_mask, inner_silhouette = (cv2.dilate(exact_distance_transform(m).astype(np.float32), disc)
                                    for m in (mask, silhouette))  # the largest inner distance within the radius
    x, y = inner_silhouette[skeleton].astype(np.float64), inner_mask[skeleton].astype(np.float64)
    delta = float(np.median(y - x))
    if np.ptp(x) > 1.0:  # y = delta + x / s: the depth's scale s apart from the offset, by a line through the pairs
        keep = np.abs(y - x - delta) < 2.0 * full_side / config.reference_side + 1.0
        for _ in range(3):
            if keep.sum() < 10 or np.ptp(x[keep]) <= 1.0:
                break
            slope, delta = np.polyfit(x[keep], y[keep], 1)
            keep = np.abs(y - slope * x - delta) < 1.0 + 0.5 * full_side / config.reference_side
    delta *= config.reference_side / full_side
    if not config.boundary_offset_min_px <= abs(delta) <= config.boundary_offset_max_px:
        return 0.0  # within the estimate's noise, or beyond what a segmenter does: the pose is the likelier culprit
    return delta


def _mask_level_set(mask: np.ndarray, delta_px: float, inside: np.ndarray | None = None,
                    outside: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` bool: the pixels of ``mask`` more than ``delta_px`` inside its edge (``delta_px > 0``), or the
    mask and the pixels less than ``-delta_px`` outside it (``delta_px < 0``); the edge lies half a pixel from the
    centres of the pixels either side of it. The mask itself when the level set would be empty. ``inside`` /
    ``outside``: the distances to that edge from the mask's / the background's pixels, ``(H, W)``, computed when
    not given (``_LevelSets`` keeps them)."""
    if delta_px == 0.0 or mask.all():
        return mask
    if delta_px > 0:
        inside = exact_distance_transform(mask) - 0.5 if inside is None else inside
        level = mask & (inside > delta_px)
    elif outside is not None:
        level = mask | (outside < -delta_px)
    else:  # only the pixels within -delta_px of the mask join it: their distances, on the mask's box grown so far
        window = foreground_window(mask, math.ceil(-delta_px) + 1)
        level = mask.copy()
        if window is not None:
            level[window] |= exact_distance_transform(~mask[window]) - 0.5 < -delta_px
    return level if level.any() else mask


def _distance_term(mask: np.ndarray, config: PoseFitConfig) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(D, W)``, ``(H, W)`` float64 each: ``W`` the mask term's weights, ``weight_hidden`` more than
    ``hidden_margin_px`` (reference pixels) outside ``mask (H, W)`` bool and 1 elsewhere (``None`` when
    ``weight_hidden`` is 1); ``D`` the distance of every pixel to the mask in reference pixels over ``gamma``,
    times ``W`` (``L_dist``'s weights, ``_StageTarget.distance``; module docstring, Hidden parts)."""
    distance = distance_to_mask(torch.from_numpy(mask)).to(torch.float64) * (config.reference_side / max(mask.shape))
    if config.weight_hidden == 1.0:
        return distance / config.gamma, None
    weight = torch.where(distance > config.hidden_margin_px, config.weight_hidden, 1.0).to(torch.float64)
    return weight * distance / config.gamma, weight


class _LevelSets:
    """The level sets of one working-resolution mask (``_mask_level_set``), with their distance terms as
    ``_StageTarget`` has them, for the polish's fit of the boundary offset; each computed once.

    With ``coverage_of`` (a ``(size, full-resolution mask)`` pair, for a ``coverage_target``) the level sets are cut
    from the full-resolution mask and the target is each working pixel's share of them, as ``_StageTarget``'s
    mask is with that setting (the distance term and weights from the pixels at least half covered): the level set
    at 0 is then the stage's own target."""

    def __init__(self, mask: np.ndarray, config: PoseFitConfig,
                 coverage_of: tuple[tuple[int, int], np.ndarray] | None = None) -> None:
        self.size, self.scale = mask.shape, 1.0  # full-resolution pixels per working pixel
        if coverage_of is not None and coverage_of[1].shape != coverage_of[0]:
            self.size, mask = coverage_of
            self.scale = max(mask.shape) / max(self.size)
        self.mask, self.config = mask, config
        self.inside = exact_distance_transform(mask) - 0.5  # > delta: inside the level set delta > 0
        self.outside = exact_distance_transform(~mask) - 0.5  # < -delta: inside the level set delta < 0
        self.steps_in, self.steps_out = np.unique(self.inside[mask]), np.unique(self.outside[~mask])
        self.cache: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}

    def at(self, delta_px: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``(mask, distance, weight)``, ``(h, w)`` float64 each (weight ``None`` for ones): the level set
        ``delta_px`` working pixels inside the mask's edge (outside for ``delta_px < 0``; the mask itself if it
        would be empty; its coverage with ``coverage_of``) and its distance term and weights
        (``_distance_term``)."""
        delta = delta_px * self.scale
        if delta > 0:  # the level sets change only where delta passes a distance the mask has
            key = (1, int(np.searchsorted(self.steps_in, delta, side="right")))
        else:
            key = (-1, int(np.searchsorted(self.steps_out, -delta, side="left")))
        if key not in self.cache:
            level = _mask_level_set(self.mask, delta, self.inside, self.outside)
            if self.scale == 1.0:
                self.cache[key] = (torch.from_numpy(level).to(torch.float64), *_distance_term(level, self.config))
            else:
                coverage = _mask_coverage(level, self.size)
                self.cache[key] = (torch.from_numpy(coverage).to(torch.float64),
                                   *_distance_term(_half_covered(coverage), self.config))
        return self.cache[key]


def _mask_coverage(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(h, w)`` float32: the share of each pixel of ``size (h, w)`` that ``mask (H, W)`` covers (area average)."""
    return cv2.resize(mask.astype(np.float32), (size[1], size[0]), interpolation=cv2.INTER_AREA)


def _resize_mask(mask: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``mask (H, W)`` bool at ``size (h, w)``: the pixels at least half covered (``cv2.resize``'s pixel
    convention); a mask thinner than a pixel keeps every pixel it touches."""
    return mask if size == mask.shape else _half_covered(_mask_coverage(mask, size))


def _half_covered(coverage: np.ndarray) -> np.ndarray:
    """``(h, w)`` bool: the pixels of a :func:`_mask_coverage` at least half covered, or every pixel it touches
    where none is (a mask thinner than a pixel)."""
    small = coverage >= 0.5
    return small if small.any() else coverage > 0


@dataclass(frozen=True, eq=False)
class _LinkGeometry:
    """What a model's link meshes give every fit, whatever the joint values: built once per model and hull budget."""

    closed: bool  # the mesh is closed and consistently wound (back faces may be culled)
    hull_verts_link: torch.Tensor  # (Vh, 3) float64 per-link convex hulls, each in its link's frame
    hull_link_index: torch.Tensor  # (Vh,) int64 link of each hull vertex
    hull_faces: torch.Tensor  # (Fh, 3) int64


_LINK_GEOMETRY: "weakref.WeakKeyDictionary[ManipulatorModel, dict[int, _LinkGeometry]]" = weakref.WeakKeyDictionary()


def _link_geometry(model: ManipulatorModel, hull_points: int) -> _LinkGeometry:
    """The model's :class:`_LinkGeometry` with hulls of at most ``hull_points`` vertices per link, computed on first
    use and kept while the model lives (a hull of a link's vertices moves with the link, and closedness is the
    faces' alone: neither depends on the joints)."""
    by_budget = _LINK_GEOMETRY.setdefault(model, {})
    links = by_budget.get(hull_points)
    if links is None:
        verts, faces, owner = _link_hulls(model.verts_link.cpu().double(), model.vert_link_index.cpu(), hull_points)
        closed = (next(iter(by_budget.values())).closed if by_budget
                  else _closed_and_consistent(model.verts_link.cpu(), model.faces.cpu()))
        links = by_budget[hull_points] = _LinkGeometry(closed=closed, hull_verts_link=verts, hull_link_index=owner,
                                                       hull_faces=faces)
    return links


def _link_hulls(verts: torch.Tensor, vert_link_index: torch.Tensor, max_points: int = 48
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The convex hull of each link's vertices ``verts (V, 3)`` (any frame that moves with the link), as one mesh
    ``(verts (Vh, 3), faces (Fh, 3))`` (closed, wound outwards) and each hull vertex's link ``(Vh,)``. A link with
    more hull vertices than ``max_points`` keeps that many of them, spread by farthest-point sampling (at most
    ``2 max_points - 4`` faces), their hull scaled about the full hull's centre of mass to the full hull's volume
    (the points' own hull is smaller, which would draw the robot smaller and pull the coarse stages nearer)."""
    import trimesh

    hull_verts, faces, links, count = [], [], [], 0
    points = verts.numpy()
    owner = vert_link_index.numpy()
    for link in np.unique(owner):
        hull = trimesh.convex.convex_hull(points[owner == link])
        if len(hull.vertices) > max_points:
            full, hull = hull, trimesh.convex.convex_hull(_farthest_points(np.asarray(hull.vertices), max_points))
            if hull.volume > 0:  # grown about the full hull's centre to its volume: no bias to a nearer pose
                scale = min(float(full.volume / hull.volume), 8.0) ** (1.0 / 3.0)
                centre = full.center_mass
                hull = trimesh.Trimesh((np.asarray(hull.vertices) - centre) * scale + centre, hull.faces, process=False)
        hull_verts.append(np.asarray(hull.vertices))
        faces.append(np.asarray(hull.faces, dtype=np.int64) + count)
        links.append(np.full(len(hull.vertices), link, dtype=np.int64))
        count += len(hull.vertices)
    return (torch.from_numpy(np.concatenate(hull_verts)), torch.from_numpy(np.concatenate(faces)),
            torch.from_numpy(np.concatenate(links)))


def _farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """``count`` of ``points (N, 3)`` chosen greedily, each the farthest from those already chosen."""
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)  # (N,) to the nearest chosen point
    for _ in range(count - 1):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


def _translation(placement: torch.Tensor) -> torch.Tensor:
    """``(S, 3)`` = (a, b, log z) -> ``t = z (a, b, 1)``."""
    z = torch.exp(placement[:, 2:3])
    return torch.cat([placement[:, :2] * z, z], dim=1)


def _closed_and_consistent(verts: torch.Tensor, faces: torch.Tensor) -> bool:
    """Whether the mesh ``verts (V, 3)``, ``faces (F, 3)`` is closed and all its faces wind the same way (so front
    faces cover its silhouette): trimesh's edge checks on the faces as given (``process=False``)."""
    import trimesh

    mesh = trimesh.Trimesh(verts.numpy(), faces.numpy(), process=False)
    return bool(mesh.is_watertight and mesh.is_winding_consistent)


def _check_joint_angles(joint_angles: torch.Tensor, model: ManipulatorModel) -> torch.Tensor:
    J = len(model.joint_names)
    if not isinstance(joint_angles, torch.Tensor):
        raise ShapeError(f"joint_angles: expected a ({J},) torch.Tensor in the order {model.joint_names}, got "
                         f"{type(joint_angles).__name__} (use estimate_pose_from_readings for readings by name)")
    check_shape(joint_angles, (J,), f"joint_angles (joints {', '.join(model.joint_names)})")
    if not joint_angles.is_floating_point() or not bool(torch.isfinite(joint_angles).all()):
        raise ShapeError("joint_angles: expected finite floating point values")
    return joint_angles.detach().to(torch.float64).cpu()
