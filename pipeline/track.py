"""Video tracking: the shape of a soft arm over a sequence of masks, each frame warm-started from the last.

Convention: as ``pipeline.shape_estimation`` (undistorted camera frame, OpenCV axes, metres; pixels of the
undistorted image).

Method (:class:`ShapeTracker`, :func:`track_shape`):

1. The first frame, and any frame with no estimate before it, gets a full fit (``ShapeTrackConfig.full_fit``:
   hypotheses from the mask, pre-fit, multi-start), as ``reconstruct_shape`` does on one image.
2. Every later frame starts from the last estimate's control points (``reconstruct_shape``'s
   ``initial_control_points_cam_m``) and, beside it, from a fresh depth hypothesis built from the mask
   (``warm_fit.warm_hypotheses``): a pre-fit (a few Levenberg-Marquardt steps on the skeleton's loss) and few
   rendered iterations (``warm_fit``), the lower loss kept, the
   base end of the skeleton taken nearest the last estimate's projected base (so base and tip never swap). Where
   the mask has several large components (a segmenter marking clutter as well), the arm's is the one the last
   estimate overlaps most (``follow_arm_component``); a full fit chooses by the pre-fit (``choose_arm_component``).
3. Re-initialisation: when a warm frame's loss exceeds ``reinit_ratio`` times the running loss (an exponential
   average of the accepted frames' losses, weight ``running_weight`` on the newest), the frame is fitted again
   from scratch (``full_fit``) and the lower of the two losses is kept; the frame is marked ``reinitialised``.
   With ``drift_ratio`` (off by default for soft arms) so is a frame whose running loss, with its loss in it, has
   climbed that many times above its lowest (a track that went wrong and gets worse slowly never jumps).
4. A frame whose mask cannot be fitted (empty: the robot is not visible; a skeleton without a path) is reported
   as skipped with the reason, and tracking goes on from the last estimate. Callers that cannot read a frame at
   all (a corrupt video frame) report it with :meth:`ShapeTracker.skip`.
5. Optionally (``ShapeTrackConfig.batch_frames > 1``, :meth:`ShapeTracker.step_many`, for recorded videos) several
   warm frames are fitted together in one batch, each from the estimate before the batch, then checked in turn as
   above (a frame well above the running loss is fitted again on its own first): more frames per
   second, at some accuracy (``docs/tracking.md``). With ``ShapeTrackConfig.live`` (a camera) a batch is the
   frames that arrived while the last one was fitted, read (and segmented) by a background thread
   (:func:`arrived_frames`): one frame at a time while the fit keeps up, batches when it falls behind.
6. With ``full_fit.model="pcc"`` every frame is tracked as above with Bezier curves (warm starts, checks and
   re-initialisations compare the Bezier fits), and each accepted frame's curve is then refined into
   ``full_fit.sections`` constant-curvature sections (``refine_pcc``), starting from the curve's sections (after a
   full fit, also from its order search's other curves') and from the last frame's, for
   ``warm_fit.pcc_iterations`` rendered steps (``full_fit.pcc_iterations`` after a full fit): the frame's result is
   that PCC fit.
7. With ``full_fit.rim_offset_px="auto"`` (a segmenter's rim bias not known) the first ``rim_search_frames`` frames
   are fitted with the offset 0, then the offset is searched over their masks together (``search_rim_offset``),
   those frames are refitted at it and it is held for every fit after them.

Manipulators (:class:`PoseTracker`, :func:`track_pose`) follow the same plan with ``estimate_pose``: a full
multi-start fit first, then one start from the previous ``T_cam_root`` at a coarser working resolution
(``PoseTrackConfig.warm_fit``), re-initialised the same way (against the running loss of the warm fits alone),
and also when that running loss has climbed ``drift_ratio`` times above its lowest (a track gone wrong slowly). A
camera that does not move relative to the robot's root (``PoseTrackConfig.static_camera``) gets one
``T_cam_root`` over all frames from ``pipeline.pose_estimation.refine_static_camera``
(:meth:`PoseTracker.static_estimate`, after the frames), and with ``PoseTrackConfig.running_static`` a running one
as the frames come, refined again each time the number of tracked frames doubles (:class:`RunningStatic`). ``pipeline track shape|pose`` (``pipeline.cli.track``) add video decoding, segmentation, joints from a
CSV file and the JSONL output: ``docs/tracking.md``.

The tracker holds the last estimate and the running loss; nothing else is shared between frames, so one tracker
per video and any number of videos at once.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np
import torch

from pipeline.camera import Camera
from pipeline.checks import check_positive
from pipeline.errors import ConfigError, ShapeError
from pipeline.geometry import rotmat_to_rotvec, rotvec_to_rotmat
from pipeline.pose_estimation import (PoseFitConfig, PoseResult, PoseStage, StaticCameraConfig, StaticCameraResult,
                                      estimate_pose, pose_loss_at, refine_static_camera)
from pipeline.robots.continuum import ContinuumRobot
from pipeline.robots.manipulator import ManipulatorModel
from pipeline.segment import image_rim_offset_px, largest_component
from pipeline.shape_estimation import (RIM_SEARCH_ITERATIONS, PccParameters, RimSearch, ShapeFitConfig,
                                       ShapeResult, follow_arm_component, reconstruct_shape, reconstruct_shapes_warm,
                                       refine_pcc, search_rim_offset)

__all__ = ["ShapeTrackConfig", "TrackedShape", "ShapeTracker", "track_shape", "arrived_frames", "rim_reading",
           "DROPPED", "extrapolate_control_points",
           "PoseTrackConfig", "TrackedPose", "PoseTracker", "track_pose", "RunningStatic", "RUNNING_STATIC",
           "smoothed_pose"]

log = logging.getLogger(__name__)

WARM_PREFIT_STEPS = {"lm": 6, "adam": 100}  # a warm frame's pre-fit steps by solver (ShapeFitConfig.prefit_solver)
#: With ``full_fit.model="pcc"``: the rendered steps refining a warm frame's sections (``warm_fit.pcc_iterations``).
WARM_PCC_ITERATIONS = 30


@dataclass(frozen=True, kw_only=True)
class ShapeTrackConfig:
    """Settings of :class:`ShapeTracker`; defaults chosen by measurement (``docs/tracking.md``).

    Fields:
        full_fit: the fit of the first frame and of re-initialised frames (``reconstruct_shape``'s defaults); its
            ``model`` is the tracker's: with ``"pcc"`` (``pcc_start="bezier"`` only) the frames are tracked with
            Bezier curves (``order`` and the warm fit as for ``"bezier"``) and each frame's curve is refined into
            ``sections`` constant-curvature sections (``refine_pcc``, with ``full_fit``'s settings), for
            ``pcc_iterations`` steps after a full fit and ``warm_fit.pcc_iterations`` after a warm one. With
            ``rim_offset_px="auto"`` the rim offset is searched over the first ``rim_search_frames`` fitted frames
            together (``search_rim_offset``; they are fitted with 0 until then) and held for every fit after them
            (a segmenter's bias does not change from frame to frame; ``warm_fit.rim_offset_px`` is then not used).
            With ``rim_offset_px="image"`` it is read from the frames' images (``ShapeTracker.read_rim``, which
            ``track_shape`` calls on each segmented frame): the median of the first ``rim_search_frames`` readings
            so far, held for every fit (full and warm) after them.
        warm_fit: the fit of every other frame, from the last estimate (its ``starts`` and ``prefit_starts`` are
            not used; its ``model`` must be ``"bezier"``, and of its PCC fields only ``pcc_iterations`` is used),
            beside the mask's straight-line depth hypothesis (``warm_hypotheses=(1,)``, both run every step:
            without it the tracked frames keep a neighbouring basin's depth profile; with it 0.74 against 1.23 px
            and 3.4 against 4.7 mm on tuning videos, for 15 % more time). Its pre-fit (no rendering, cheap)
            matters: the rendered loss alone barely sees the arm's depth, which then drifts from frame to
            frame; the pre-fit's width term holds it. Since 2026-11-27 the pre-fit takes a few
            Levenberg-Marquardt steps (``prefit_solver="lm"``, at most 6 since session 66; before, 100 Adam
            steps) and the last estimate also starts as it is (``warm_keep_start``): on the tuning videos a warm
            frame 0.66-0.76 -> 0.31 s, the tracked frames 0.84 -> 0.61 px and 3.7 -> 2.7 mm (from segmented frames
            about as before). Its rate is a full fit's (``lr_control`` 0.01 decaying to a tenth): a fifth of it,
            decaying to half, tracked slow single-bend and S-shaped arms closer and two-section arms farther
            (``docs/tracking.md``).
        reinit_ratio: a warm frame whose loss is above this times the running loss is fitted again with
            ``full_fit`` (> 1).
        running_weight: weight of the newest accepted loss in the running loss (exponential average), in (0, 1].
        drift_ratio: a warm frame under ``reinit_ratio`` whose running loss, with its own loss in it, is above
            this times the lowest running loss since the track last started is fitted again with ``full_fit`` too
            (a track gone wrong slowly raises its running loss with it and never jumps; ``PoseTrackConfig``'s rule).
            The lower loss is kept; when it is the full fit's, the running loss and its lowest restart at it, and
            when it is not, the higher level is accepted (the lowest restarts at the running loss). ``None`` (the
            default): off; else > 1. Off because a soft arm's loss changes with its shape: on tuning videos of
            two-section arms the running loss of tracks that were not lost rose 2.9-3.8x above its lowest over a
            bending cycle, and at 3 the rule fitted two frames afresh for nothing (``docs/tracking.md``);
            single-bend arms stayed within 1.2-1.5x.
        fixed_base: hold the base point and the base direction (first control point, direction to the second)
            found on the first tracked frame in every later fit (``reconstruct_shape``'s ``fixed_base_cam_m``),
            for an arm whose base does not move relative to the camera.
        predict: start each warm fit from a constant-velocity prediction of the control points (the last
            estimate plus its change since the one before, scaled by the frame gap) instead of the last estimate
            itself, once there are two estimates since the last full fit (that fit's included).
        batch_frames: warm frames fitted together in one batch (``ShapeTracker.step_many``,
            ``reconstruct_shapes_warm``): every frame of a batch starts from the estimate before the batch (or its
            prediction), and a step's cost is shared; 1 fits each frame as it comes. With ``live``, the most frames
            a batch takes.
            The batch's fit leaves out ``warm_fit.warm_keep_start`` (the start before the batch is stale for its
            later frames); a frame fitted again on its own (``batch_retry_ratio``) keeps it.
            ``track_shape`` then yields a batch's frames together. Not with ``warm_fit.compile`` (a ``ConfigError``:
            every batch would compile anew).
        batch_retry_ratio: a batch frame whose loss is above this times the running loss is fitted again on its
            own, from the frame before it (the warm fit of ``batch_frames=1``), and the lower loss kept: a batch's
            frames all start from the estimate before the batch, which fast motion can leave behind (> 1).
        live: the frames come from a live source (a camera): ``track_shape`` reads them, and segments them with its
            ``segmenter``, in a background thread while it fits, and each batch is every frame that arrived
            meanwhile, at most ``batch_frames`` (:func:`arrived_frames`): a single frame is fitted as with
            ``batch_frames=1``, so the tracker runs one frame at a time while it keeps up and in batches when the
            camera is faster than one frame's fit; each result comes about one batch's fit after its frame. False
            (a recorded video): batches of ``batch_frames`` frames, waited for.
        drop_late: with ``live``, when ``batch_frames`` frames already wait for the tracker, the oldest of them is
            dropped for the newest (reported as skipped, ``DROPPED``), so that a tracker slower than the camera
            stays within about a batch of it instead of falling further behind; False (default): every frame is
            tracked, and a slower tracker's delay grows (the camera's own buffer holds, or drops, its frames).
            With it the segmenter runs on the frames kept only, in the fitting thread.
        rim_search_frames: with ``full_fit.rim_offset_px="auto"``, the number of fitted frames whose masks the rim
            offset is searched over (>= 1): their fits are then replaced by their refits at the offset found
            (``ShapeTracker.rim_refits``; ``track_shape`` yields them only then). One frame found the right offset
            on 15 of 18 tuning cases, 8 frames on 18 (``docs/tracking.md``). With ``"image"``: the number of
            frames whose readings are taken (each frame fitted at the median of the readings so far).
        carry_moments: each warm fit's Adam begins with the state the last estimate's fit ended with
            (``ShapeResult.moments``: its running averages of the gradients and their squares, and its step count;
            a batch's frames all begin with the state before the batch) instead of zeros, from which Adam's first
            steps move every coordinate by about the full rate. An option, off by default: on tuning videos of
            single-bend and S-shaped Bezier arms the tracked frames came nearer in 2D (24 videos, 0.877 -> 0.799 px
            over all frames one at a time, 1.122 -> 1.021 in batches of 8, 19 of 24 nearer each way, 3D about
            the same), on two-section arms farther (12 videos, 1.308 -> 1.502 px, one track lost to a wrong basin)
            and at 60 warm steps no nearer (``docs/tracking.md``).
    """

    full_fit: ShapeFitConfig = ShapeFitConfig(model="bezier")
    warm_fit: ShapeFitConfig = ShapeFitConfig(model="bezier", iterations=30, starts=1,
                                              prefit_iterations=WARM_PREFIT_STEPS["lm"], prefit_solver="lm",
                                              warm_hypotheses=(1,), warm_keep_start=True, multi_start_fraction=1.0,
                                              pcc_iterations=WARM_PCC_ITERATIONS)
    reinit_ratio: float = 3.0
    running_weight: float = 0.3
    drift_ratio: float | None = None
    fixed_base: bool = False
    predict: bool = False
    batch_frames: int = 1
    batch_retry_ratio: float = 1.5
    live: bool = False
    drop_late: bool = False
    rim_search_frames: int = 8
    carry_moments: bool = False

    def __post_init__(self) -> None:
        if (not isinstance(self.rim_search_frames, int) or isinstance(self.rim_search_frames, bool)
                or self.rim_search_frames < 1):
            raise ConfigError(f"rim_search_frames: expected an int >= 1, got {self.rim_search_frames!r}")
        if not isinstance(self.batch_frames, int) or isinstance(self.batch_frames, bool) or self.batch_frames < 1:
            raise ConfigError(f"batch_frames: expected an int >= 1, got {self.batch_frames!r}")
        for name in ("live", "drop_late", "carry_moments"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}: expected True or False, got {getattr(self, name)!r}")
        if self.drop_late and not self.live:
            raise ConfigError("drop_late: frames are dropped from a live source only; set live=True too")
        if self.batch_frames > 1 and isinstance(self.warm_fit, ShapeFitConfig) and self.warm_fit.compile:
            raise ConfigError("batch_frames > 1 with warm_fit.compile: a batch's working image changes size from batch "
                              "to batch and torch.compile recompiles for each (minutes), for about 15 % less time per "
                              "frame once compiled; use one or the other (docs/tracking.md)")
        for name in ("full_fit", "warm_fit"):
            if not isinstance(getattr(self, name), ShapeFitConfig):
                raise ConfigError(f"{name}: expected a ShapeFitConfig, got {type(getattr(self, name)).__name__}")
        if self.warm_fit.model != "bezier":
            raise ConfigError(f"warm_fit.model: the warm frames are Bezier fits, expected 'bezier', got "
                              f"{self.warm_fit.model!r} (set model='bezier'; ShapeFitConfig's default is 'auto'); "
                              f"set full_fit.model='pcc' to track PCC sections")
        if self.full_fit.model == "auto":
            raise ConfigError("full_fit.model: 'auto' chooses the model image by image, a tracker keeps one model for "
                              "the whole video; expected 'bezier' or 'pcc' (ShapeFitConfig's default is 'auto': set "
                              "model=...)")
        if self.full_fit.model == "pcc" and self.full_fit.pcc_start != "bezier":
            raise ConfigError(f"full_fit.pcc_start: a tracker refines each frame's Bezier fit into sections, expected "
                              f"'bezier', got {self.full_fit.pcc_start!r}")
        if self.warm_fit.rim_offset_px in ("auto", "image"):
            raise ConfigError(f"warm_fit.rim_offset_px: {self.warm_fit.rim_offset_px!r} is set on full_fit (the warm "
                              f"fits then hold the offset the first frames gave) or give a number")
        for name in ("reinit_ratio", "batch_retry_ratio"):
            value = float(getattr(self, name))
            if not (value > 1.0 and math.isfinite(value)):
                raise ConfigError(f"{name}: expected a finite number > 1, got {getattr(self, name)!r}")
        if not 0.0 < float(self.running_weight) <= 1.0:
            raise ConfigError(f"running_weight: expected a number in (0, 1], got {self.running_weight!r}")
        _check_drift_ratio(self.drift_ratio)


def _check_drift_ratio(ratio: object) -> None:
    """``drift_ratio`` of either tracker's config: a finite number > 1, or ``None`` (off)."""
    if ratio is not None and not (isinstance(ratio, (int, float)) and not isinstance(ratio, bool)
                                  and float(ratio) > 1.0 and math.isfinite(float(ratio))):
        raise ConfigError(f"drift_ratio: expected a finite number > 1 or None (off), got {ratio!r}")


@dataclass(frozen=True, kw_only=True)
class TrackedShape:
    """One frame's outcome.

    Fields:
        frame: the frame's index in the video (as the caller numbers them).
        time_s: its time in the video, seconds, or ``None`` meaning *unknown* (frames without a frame rate).
        result: the estimate, or ``None`` when the frame was skipped.
        reinitialised: the frame was fitted from scratch because its warm-started loss jumped (not set on the
            first frame, whose full fit is the plan).
        skipped: ``None``, or why the frame has no estimate (e.g. ``"mask is empty ..."``).
        iterations: Adam iterations spent on the frame (warm and full fits together; 0 when skipped).
        seconds: wall time of the frame's fit(s).
        model: the tracker's model (``ShapeTrackConfig.full_fit.model``): with ``"pcc"`` the result is a PCC fit
            and the frame's line has ``"pcc"`` (its sections, ``None`` when skipped).
    """

    frame: int
    time_s: float | None
    result: ShapeResult | None
    reinitialised: bool
    skipped: str | None
    iterations: int
    seconds: float
    model: str = "bezier"

    def to_dict(self) -> dict:
        """The frame's line of ``pipeline track shape --out TRAJ.jsonl`` (arrays as nested lists, ``None`` for
        the estimate of a skipped frame)."""
        r = self.result
        return {
            "frame": self.frame,
            "time_s": self.time_s,
            "control_points_cam_m": None if r is None else r.control_points_cam_m,
            "radii_m": None if r is None else r.radii_m,
            "centerline_cam_m": None if r is None else r.centerline_cam_m,
            "loss": None if r is None else r.loss,
            "rim_offset_px": None if r is None else r.rim_offset_px,
            **({"pcc": None if r is None else r.pcc.to_dict()} if self.model == "pcc" else {}),
            "iterations": self.iterations,
            "seconds": self.seconds,
            "reinitialised": self.reinitialised,
            "skipped": self.skipped,
        }


class _RunningLoss:
    """The running loss both trackers hold (``running_loss``, ``lowest_running_loss``, under ``config``'s
    ``running_weight`` and ``drift_ratio``), and the Adam state both carry to their warm fits (``_moments``)."""

    running_loss: float | None
    lowest_running_loss: float | None

    def _moments(self) -> dict | None:
        """The Adam state a warm fit begins with: the last estimate's (``config.carry_moments``), else ``None``."""
        return self.last.moments if self.config.carry_moments else None

    def _running_with(self, loss: float) -> float:
        """The running loss with ``loss`` in it (an exponential average, ``config.running_weight`` on ``loss``)."""
        weight = self.config.running_weight
        return (1.0 - weight) * self.running_loss + weight * loss

    def _drifted(self, loss: float) -> bool:
        """Whether the running loss with a warm frame's ``loss`` in it has climbed above ``config.drift_ratio``
        times its lowest since the last restart (never with ``drift_ratio=None`` or before a running loss)."""
        ratio = self.config.drift_ratio
        return ratio is not None and self.running_loss is not None and (
            self._running_with(loss) > ratio * self.lowest_running_loss)

    def _level_check(self, loss: float, frame: int) -> tuple[bool, bool]:
        """``(jumped, drifted)`` of a warm frame's ``loss``: above ``config.reinit_ratio`` times the running loss,
        or else (``_drifted``) the running loss with it above ``config.drift_ratio`` times its lowest. Logs the full
        fit either calls for and counts the drift rule's in ``drift_reinitialisations``."""
        config = self.config
        jumped = self.running_loss is not None and loss > config.reinit_ratio * self.running_loss
        drifted = not jumped and self._drifted(loss)
        if jumped:
            log.info("frame %d: loss %.4g above %.1f x the running loss %.4g: full fit", frame, loss,
                     config.reinit_ratio, self.running_loss)
        elif drifted:
            log.info("frame %d: running loss %.4g above %.1f x its lowest %.4g: full fit", frame,
                     self._running_with(loss), config.drift_ratio, self.lowest_running_loss)
            self.drift_reinitialisations += 1
        return jumped, drifted


class ShapeTracker(_RunningLoss):
    """Tracks one soft arm through one video, frame by frame (module docstring, Method).

    Example (a live camera; ``segmenter`` makes a mask from a BGR image)::

        tracker, tips = ShapeTracker(robot, camera), []
        for i, image in enumerate(frames):
            tracked = tracker.step(segmenter(image, frame_index=i), frame=i)
            if tracked.result is not None:
                tips.append(tracked.result.centerline_cam_m[-1])  # the tip, camera frame, metres
    """

    def __init__(
        self,
        robot: ContinuumRobot,
        camera: Camera,
        config: ShapeTrackConfig = ShapeTrackConfig(),
        *,
        base_pixel: tuple[float, float] | None = None,
    ) -> None:
        """Args:
            robot, camera: as ``reconstruct_shape`` takes them.
            config: tracking settings.
            base_pixel: ``(u, v)`` of the base in the undistorted image for full fits, or ``None`` meaning
                *unknown* (``reconstruct_shape``'s rule: the path end nearer the image border).
        """
        if not isinstance(config, ShapeTrackConfig):
            raise ConfigError(f"config: expected a ShapeTrackConfig, got {type(config).__name__}")
        self.robot = robot
        self.camera = camera
        self.config = config
        self.base_pixel = base_pixel
        self.last: ShapeResult | None = None  # a Bezier fit, also with full_fit.model "pcc"
        self.last_pcc: PccParameters | None = None  # with full_fit.model "pcc": the last frame's sections
        self.recent: list[tuple[int, np.ndarray]] = []  # (frame, control points) since the last full fit, <= 2
        self.base: np.ndarray | None = None  # (2, 3) base point and direction held with config.fixed_base
        self.running_loss: float | None = None
        self.lowest_running_loss: float | None = None  # since the running loss last (re)started: drift_ratio
        self.reinitialisations = 0
        self.drift_reinitialisations = 0  # of those, the ones drift_ratio triggered
        self.batch_retries = 0  # batch frames fitted again on their own (``config.batch_retry_ratio``)
        self.rim_offset: float | None = None  # with full_fit.rim_offset_px "auto": the search's, once it ran
        self.rim_search: RimSearch | None = None  # ... and the search itself
        self.rim_refits: dict[int, TrackedShape] = {}  # the searched frames, as refitted at its offset
        self._rim_frames: list[tuple[np.ndarray, TrackedShape]] = []  # (mask, outcome) of the frames it will use
        self.rim_readings: list[float] = []  # with full_fit.rim_offset_px "image": read_rim's (<= rim_search_frames)
        self._rim_read_tried = False
        self.skipped = 0

    def read_rim(self, image: np.ndarray, mask: np.ndarray) -> None:
        """With ``full_fit.rim_offset_px="image"``: read a segmented frame's rim offset from its ``(H, W, 3)``
        uint8 BGR image and its ``(H, W)`` bool mask (``pipeline.segment.image_rim_offset_px`` on the mask's largest
        component, the arm's as a rule) and keep it in ``rim_readings``, up to ``rim_search_frames`` readings; the
        fits use their median so far. Call it before ``step`` with each frame (``track_shape`` does, also from a
        live reader's thread). Otherwise, after enough readings, or for an empty mask it does nothing."""
        if self.config.full_fit.rim_offset_px != "image" or len(self.rim_readings) >= self.config.rim_search_frames:
            return
        self._rim_read_tried = True
        if isinstance(mask, np.ndarray) and mask.dtype == bool and mask.any():
            self.rim_readings.append(image_rim_offset_px(image, largest_component(mask)))

    @property
    def rim_search_pending(self) -> bool:
        """Whether the rim offset is still to be searched (``full_fit.rim_offset_px="auto"``, too few frames yet):
        the frames fitted so far have the offset 0 and get their refits once it has run."""
        return self.config.full_fit.rim_offset_px == "auto" and self.rim_offset is None

    def step(self, mask: np.ndarray, *, frame: int, time_s: float | None = None) -> TrackedShape:
        """Fit one frame's ``(H, W)`` bool mask (as taken by the camera) and return its outcome.

        A mask that cannot be fitted (``ShapeError``: empty, no skeleton path) gives a skipped frame; a
        ``ConfigError`` (a mask of the wrong size) is raised, since every later frame would fail alike. With
        ``full_fit.rim_offset_px="auto"`` the frame that completes the rim search's frames comes back refitted at
        the offset found; the frames before it are in ``rim_refits``.
        """
        t0 = time.perf_counter()
        config = self.config
        reinitialised = False
        iterations = 0
        try:
            if self.last is None:
                result = reconstruct_shape(mask, self.robot, self.camera, self._full_config(),
                                           base_pixel=self.base_pixel, fixed_base_cam_m=self.base)
                iterations = config.full_fit.iterations
            else:
                mask = self._follow(mask)
                result, reinitialised, iterations = self._checked(mask, self._warm_fit(mask, frame), frame)
        except ShapeError as error:
            log.warning("frame %d skipped: %s", frame, error)
            return self.skip(reason=str(error), frame=frame, time_s=time_s, seconds=time.perf_counter() - t0)
        tracked = self._accept(result, frame=frame, time_s=time_s, reinitialised=reinitialised, iterations=iterations,
                               seconds=time.perf_counter() - t0, mask=mask)
        self._search_rim_when_due()
        return self.rim_refits.get(frame, tracked)

    def step_many(self, masks: Sequence[np.ndarray], *, frames: Sequence[int],
                  times_s: Sequence[float | None] | None = None) -> list[TrackedShape]:
        """Fit several frames' masks, in order, the warm ones together in one batch (``reconstruct_shapes_warm``):
        each starts from the estimate before the batch (its constant-velocity prediction to that frame with
        ``config.predict``). Without an estimate yet, the first frame gets its full fit first (``step``). Then
        frame by frame as ``step``: the loss check against the running loss (a full fit when it jumps), skipped
        frames. A frame's ``seconds`` is its share of the batch (plus its own full fit, if any).

        Args:
            masks: ``(H, W)`` bool masks, as taken by the camera.
            frames: their indices in the video, increasing.
            times_s: their times, or ``None`` meaning *unknown*.
        """
        times = [None] * len(masks) if times_s is None else list(times_s)
        if not (len(masks) == len(frames) == len(times)):
            raise ConfigError(f"masks, frames, times_s: expected as many of each, got {len(masks)}, {len(frames)}, "
                              f"{len(times)}")
        out: list[TrackedShape] = []
        while masks and self.last is None:  # the first frame(s): full fits, until one gives an estimate
            out.append(self.step(masks[0], frame=frames[0], time_s=times[0]))
            masks, frames, times = masks[1:], frames[1:], times[1:]
        if not masks:
            return out
        if len(masks) == 1:
            return out + [self.step(masks[0], frame=frames[0], time_s=times[0])]
        config = self.config
        t0 = time.perf_counter()
        masks = [self._follow(mask) for mask in masks]
        base_pixel = self._projected_base(self.last)
        # Without the kept start (warm_keep_start): the start before the batch is stale for the batch's later
        # frames; on tuning videos keeping it cost 30 % more time for nothing (docs/tracking.md).
        batch_fit = replace(self._warm_config(), warm_keep_start=False)
        outcomes = reconstruct_shapes_warm(masks, self.robot, self.camera, batch_fit,
                                           initial_control_points_cam_m=[self._start(f) for f in frames],
                                           base_pixels=[base_pixel] * len(masks), fixed_base_cam_m=self.base,
                                           initial_moments=self._moments())
        share = (time.perf_counter() - t0) / len(masks)
        for mask, frame, time_s, outcome in zip(masks, frames, times, outcomes):
            if isinstance(outcome, ShapeError):
                log.warning("frame %d skipped: %s", frame, outcome)
                out.append(self.skip(reason=str(outcome), frame=frame, time_s=time_s, seconds=share))
                continue
            t1 = time.perf_counter()
            try:
                extra = 0
                if self.running_loss is not None and outcome.loss > config.batch_retry_ratio * self.running_loss:
                    log.info("frame %d: batch loss %.4g above %.2f x the running loss %.4g: fitted on its own", frame,
                             outcome.loss, config.batch_retry_ratio, self.running_loss)
                    alone = self._warm_fit(mask, frame)
                    outcome, extra = (alone if alone.loss < outcome.loss else outcome), config.warm_fit.iterations
                    self.batch_retries += 1
                result, reinitialised, iterations = self._checked(mask, outcome, frame)
                iterations += extra
            except ShapeError as error:  # as in ``step``: the frame's full fit could not use the mask
                log.warning("frame %d skipped: %s", frame, error)
                out.append(self.skip(reason=str(error), frame=frame, time_s=time_s,
                                     seconds=share + time.perf_counter() - t1))
                continue
            out.append(self._accept(result, frame=frame, time_s=time_s, reinitialised=reinitialised,
                                    iterations=iterations, seconds=share + time.perf_counter() - t1, mask=mask))
        self._search_rim_when_due()
        return [self.rim_refits.get(tracked.frame, tracked) for tracked in out]

    def _follow(self, mask: np.ndarray) -> np.ndarray:
        """``follow_arm_component`` of a warm frame's mask; a mask it cannot use (empty, not a bool array) as it is,
        for the fit to report."""
        try:
            return follow_arm_component(mask, self.last, self.camera)
        except ShapeError:
            return mask

    def _warm_fit(self, mask: np.ndarray, frame: int) -> ShapeResult:
        """The warm fit of one frame from the last estimate (``_start``), the skeleton's base end nearest its base."""
        return reconstruct_shape(mask, self.robot, self.camera, self._warm_config(),
                                 base_pixel=self._projected_base(self.last),
                                 initial_control_points_cam_m=self._start(frame), fixed_base_cam_m=self.base,
                                 initial_moments=self._moments())

    def _warm_config(self) -> ShapeFitConfig:
        """``config.warm_fit`` (``_at_searched_rim``)."""
        return self._at_searched_rim(self.config.warm_fit)

    def _full_config(self) -> ShapeFitConfig:
        """``config.full_fit`` (``_at_searched_rim``), as a Bezier fit (the frames' PCC fits refine its curve)."""
        full = self.config.full_fit
        return self._at_searched_rim(full if full.model == "bezier" else replace(full, model="bezier"))

    def _at_searched_rim(self, fit: ShapeFitConfig) -> ShapeFitConfig:
        """``fit`` as it is, or with ``full_fit.rim_offset_px="auto"`` at the searched offset (0 until found: the
        frames' search comes after them, ``search_rim_offset``), or with ``"image"`` at the median of the readings
        so far (0 before any frame had an arm to read)."""
        rim = self.config.full_fit.rim_offset_px
        if rim == "image":
            if not self._rim_read_tried:
                raise ConfigError("full_fit.rim_offset_px: 'image' reads the rim from the frames' images: call "
                                  "read_rim(image, mask) with each frame before step (track_shape does, given a "
                                  "segmenter)")
            readings = list(self.rim_readings)  # a live reader's thread may add one meanwhile
            return replace(fit, rim_offset_px=float(np.median(readings)) if readings else 0.0)
        if rim != "auto":
            return fit
        return replace(fit, rim_offset_px=self.rim_offset or 0.0)

    def _search_rim_when_due(self) -> None:
        """Search the rim offset once ``config.rim_search_frames`` frames are fitted (``finish_rim_search``)."""
        if self.rim_search_pending and len(self._rim_frames) >= self.config.rim_search_frames:
            self.finish_rim_search()

    def finish_rim_search(self) -> list[TrackedShape]:
        """Search the rim offset now over the frames fitted so far (``search_rim_offset``; e.g. at the end of a video
        shorter than ``config.rim_search_frames``), hold it, and take the refits of those frames: the last one as
        the last estimate, the running loss over them. Returns the refitted frames (``rim_refits``), in order; none
        when nothing is pending or no frame was fitted yet."""
        if not self.rim_search_pending or not self._rim_frames:
            return []
        masks = [mask for mask, _ in self._rim_frames]
        outcomes = [tracked for _, tracked in self._rim_frames]
        # Without the held base: the offset moves the whole arm in depth, its base too (set again below).
        search = search_rim_offset(masks, [tracked.result for tracked in outcomes], self.robot, self.camera,
                                   self._full_config())
        log.info("rim offset %+g px over frames %d-%d (mean losses %s)", search.offset_px, outcomes[0].frame,
                 outcomes[-1].frame, ", ".join(f"{k:+g}: {v:.4g}" for k, v in sorted(search.losses.items())))
        self.rim_offset, self.rim_search, self._rim_frames = search.offset_px, search, []
        share = search.seconds / len(outcomes)
        self.rim_refits = {tracked.frame: replace(tracked, result=result, seconds=tracked.seconds + share,
                                                  iterations=tracked.iterations + RIM_SEARCH_ITERATIONS)
                           for tracked, result in zip(outcomes, search.results)}
        if search.offset_px != 0.0:  # the estimates the next frames start from, at the offset
            self.last = search.results[-1]
            kept = {frame for frame, _ in self.recent}
            self.recent = [(t.frame, r.control_points_cam_m) for t, r in zip(outcomes, search.results)
                           if t.frame in kept]
            self.running_loss = self.lowest_running_loss = None
            for result in search.results:
                self._update_running_loss(result.loss)
            if self.base is not None:
                self.base = None
                self._hold_base(search.results[0])
        return list(self.rim_refits.values())

    def _checked(self, mask: np.ndarray, result: ShapeResult, frame: int) -> tuple[ShapeResult, bool, int]:
        """A warm fit's result against the running loss: ``(the result kept, re-initialised, iterations)``."""
        config = self.config
        iterations = config.warm_fit.iterations
        jumped, drifted = self._level_check(result.loss, frame)
        if not (jumped or drifted):
            return result, False, iterations
        # The base end nearest the last estimate's base unless the caller named it: the arm's base end does not
        # change between frames, and a mask that made the warm fit fail (a false positive at one end) can also
        # make the widths name the wrong end (docs/tracking.md).
        base_pixel = self.base_pixel if self.base_pixel is not None else self._projected_base(self.last)
        full = reconstruct_shape(mask, self.robot, self.camera, self._full_config(), base_pixel=base_pixel,
                                 fixed_base_cam_m=self.base)
        self.reinitialisations += 1
        kept = full if full.loss < result.loss else result
        if drifted:  # the level restarts (``_accept`` adds the frame): at the full fit's loss, or, where the full
            # fit did no better, at the running loss with the frame in it (the masks changed, not the track)
            if kept is full:
                self.running_loss = None
            self.lowest_running_loss = None
        return kept, True, iterations + config.full_fit.iterations

    def _accept(self, result: ShapeResult, *, frame: int, time_s: float | None, reinitialised: bool,
                iterations: int, seconds: float, mask: np.ndarray) -> TrackedShape:
        """Take ``result`` as the last estimate (the velocity, the held base, the running loss); kept with its
        ``mask`` for the rim search while that is pending."""
        config = self.config
        full = self.last is None or reinitialised
        self.last = result
        # a full fit (first frame, re-initialisation) starts the velocity afresh; warm fits keep the order
        self.recent = ([] if reinitialised else self.recent[-1:]) + [(frame, result.control_points_cam_m)]
        if config.fixed_base and self.base is None:
            self._hold_base(result)
        self._update_running_loss(result.loss)
        if config.full_fit.model == "pcc":
            t0 = time.perf_counter()
            steps = (config.full_fit if full else config.warm_fit).pcc_iterations
            result = refine_pcc(follow_arm_component(mask, result, self.camera), self.robot, self.camera,
                                config.full_fit, result, previous=self.last_pcc, iterations=steps,
                                base_pixel=self._projected_base(result), fixed_base_cam_m=self.base)
            self.last_pcc = result.pcc
            iterations, seconds = iterations + steps, seconds + time.perf_counter() - t0
        tracked = TrackedShape(frame=frame, time_s=time_s, result=result, reinitialised=reinitialised, skipped=None,
                               iterations=iterations, seconds=seconds, model=config.full_fit.model)
        if self.rim_search_pending:
            self._rim_frames.append((mask, tracked))
        return tracked

    def _hold_base(self, result: ShapeResult) -> None:
        """Hold ``result``'s base point and direction (``config.fixed_base``)."""
        c = result.control_points_cam_m
        direction = c[1] - c[0]
        self.base = np.stack([c[0], direction / max(float(np.linalg.norm(direction)), 1e-12)])

    def _update_running_loss(self, loss: float) -> None:
        """The running loss: an exponential average of accepted losses, ``config.running_weight`` on the newest;
        and its lowest since it last (re)started (``config.drift_ratio``)."""
        self.running_loss = loss if self.running_loss is None else self._running_with(loss)
        lowest = self.lowest_running_loss
        self.lowest_running_loss = self.running_loss if lowest is None else min(lowest, self.running_loss)

    def skip(self, *, reason: str, frame: int, time_s: float | None = None, seconds: float = 0.0) -> TrackedShape:
        """Record a frame without an estimate (e.g. one the video reader could not decode); tracking goes on from
        the last estimate."""
        if not isinstance(reason, str) or not reason:
            raise ConfigError(f"reason: expected a non-empty string, got {reason!r}")
        self.skipped += 1
        return TrackedShape(frame=frame, time_s=time_s, result=None, reinitialised=False, skipped=reason,
                            iterations=0, seconds=seconds, model=self.config.full_fit.model)

    def _start(self, frame: int) -> np.ndarray:
        """The warm fit's start ``(n+1, 3)``: the last estimate's control points, or with ``config.predict``
        their extrapolation to ``frame`` (``extrapolate_control_points``)."""
        return extrapolate_control_points(self.recent, frame) if self.config.predict else self.recent[-1][1]

    @staticmethod
    def _projected_base(result: ShapeResult) -> tuple[float, float]:
        """The estimate's base point in the undistorted image, ``(u, v)`` pixels."""
        p = result.camera.K_array() @ result.control_points_cam_m[0]
        return (float(p[0] / p[2]), float(p[1] / p[2]))


def extrapolate_control_points(recent: list[tuple[int, np.ndarray]], frame: int) -> np.ndarray:
    """Constant-velocity prediction of a soft arm's control points at ``frame``.

    Args:
        recent: one or two ``(frame index, (n+1, 3) control points)`` estimates, oldest first (camera frame,
            metres).
        frame: the frame to predict, after the last one.

    Returns:
        ``(n+1, 3)``: ``c_last + (c_last - c_before) * (frame - f_last) / (f_last - f_before)``; the last estimate
        itself with a single estimate, estimates of different orders, a frame not after the last, or where a
        predicted control point would not be in front of the camera (depth <= 0).
    """
    last_frame, last = recent[-1]
    if len(recent) < 2 or frame <= last_frame or recent[0][1].shape != last.shape or recent[0][0] >= last_frame:
        return last
    before_frame, before = recent[0]
    predicted = last + (last - before) * ((frame - last_frame) / (last_frame - before_frame))
    return predicted if (predicted[:, 2] > 0).all() else last


def track_shape(
    frames: Iterable[np.ndarray],
    robot: ContinuumRobot,
    camera: Camera,
    config: ShapeTrackConfig = ShapeTrackConfig(),
    *,
    segmenter: Callable[..., np.ndarray] | None = None,
    base_pixel: tuple[float, float] | None = None,
    fps: float | None = None,
) -> Iterator[TrackedShape]:
    """Track a soft arm through ``frames``, yielding each frame's outcome as soon as it is done.

    Args:
        frames: any iterable (a list, a video reader, a live camera loop) of ``(H, W)`` bool masks, or of
            ``(H, W, 3)`` uint8 BGR images when ``segmenter`` is given; numbered 0, 1, ...
        robot, camera: as ``reconstruct_shape`` takes them.
        config: tracking settings.
        segmenter: ``segmenter(image, frame_index=i) -> (H, W) bool mask`` (``pipeline.segment``), or ``None``
            meaning *the frames are masks*.
        base_pixel: see :class:`ShapeTracker`.
        fps: frame rate, for ``time_s = i / fps``; ``None`` meaning *unknown* (``time_s`` is ``None``).

    Yields:
        TrackedShape per frame, in order. With ``config.full_fit.rim_offset_px="auto"`` the first
        ``config.rim_search_frames`` frames come together, once the rim offset is searched over them (refitted at
        it). With ``config.live`` the frames are read (and segmented) by a background thread, and a batch's frames
        come together (``ShapeTrackConfig.live``).
    """
    if fps is not None:
        check_positive(fps, "fps")
    if config.full_fit.rim_offset_px == "image" and segmenter is None:
        raise ConfigError("config.full_fit.rim_offset_px: 'image' reads the rim from the frames' images; give a "
                          "segmenter (the frames are masks here) or a number")
    tracker = ShapeTracker(robot, camera, config, base_pixel=base_pixel)
    if segmenter is not None:
        segmenter = rim_reading(tracker, segmenter)
    held: list[TrackedShape] = []  # frames done while the rim search waits for more (their refits come with it)

    def release(done: list[TrackedShape]) -> list[TrackedShape]:
        nonlocal held
        held += done
        if tracker.rim_search_pending:
            return []
        out, held = [tracker.rim_refits.get(tracked.frame, tracked) for tracked in held], []
        return out

    if config.live:
        for group in arrived_frames(frames, config.batch_frames, segmenter, drop_oldest=config.drop_late):
            dropped = [tracker.skip(reason=DROPPED, frame=i, time_s=None if fps is None else i / fps)
                       for i, mask in group if mask is None]  # older than the group's other frames
            yield from release(dropped + _step_batch(tracker, [(i, m) for i, m in group if m is not None], fps))
        tracker.finish_rim_search()
        yield from (tracker.rim_refits.get(tracked.frame, tracked) for tracked in held)
        return
    batch: list[tuple[int, np.ndarray]] = []
    for i, frame in enumerate(frames):
        mask = frame if segmenter is None else segmenter(frame, frame_index=i)
        if config.batch_frames == 1:
            yield from release([tracker.step(mask, frame=i, time_s=None if fps is None else i / fps)])
            continue
        batch.append((i, mask))
        if len(batch) == config.batch_frames or tracker.last is None:
            yield from release(_step_batch(tracker, batch, fps))
            batch = []
    held += _step_batch(tracker, batch, fps)
    tracker.finish_rim_search()  # a video shorter than the rim search's frames (or none fitted: nothing to search)
    yield from (tracker.rim_refits.get(tracked.frame, tracked) for tracked in held)


def rim_reading(tracker: ShapeTracker, segmenter: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """``segmenter`` that also hands each frame's image and mask to ``tracker.read_rim`` (with
    ``full_fit.rim_offset_px="image"``; else ``segmenter`` itself)."""
    if tracker.config.full_fit.rim_offset_px != "image":
        return segmenter

    def segment(image: np.ndarray, *, frame_index: int = 0) -> np.ndarray:
        mask = segmenter(image, frame_index=frame_index)
        tracker.read_rim(image, mask)
        return mask

    return segment


#: The ``skipped`` reason of a frame a live tracker dropped (``ShapeTrackConfig.drop_late``).
DROPPED = "dropped: the tracker was a batch behind the camera (drop_late)"


class _End:
    """What the reader of :func:`arrived_frames` puts after the last frame: the end, or the error it raised."""

    def __init__(self, error: BaseException | None = None) -> None:
        self.error = error


def arrived_frames(frames: Iterable[np.ndarray], most: int, segmenter: Callable[..., np.ndarray] | None = None,
                   *, drop_oldest: bool = False) -> Iterator[list[tuple[int, np.ndarray | None]]]:
    """The frames of a live source in groups: each group is every frame that arrived while the caller worked on
    the group before (at least one, waited for; at most ``most``), as ``(index, mask)`` pairs in order, numbered
    0, 1, ... A background thread reads ``frames`` (and runs ``segmenter(image, frame_index=i)`` on each, when
    given) and holds at most ``most`` frames ahead (a faster source, e.g. a recorded video, then waits: nothing
    piles up in memory). An error raised by the source or the segmenter is raised here, after the frames before it;
    when the caller stops early, the thread stops at its next frame.

    Args:
        frames: any iterable of masks, or of images with ``segmenter``.
        most: the largest group (>= 1).
        segmenter: ``segmenter(image, frame_index=i) -> (H, W) bool``, or ``None`` meaning *the frames are masks*.
        drop_oldest: when ``most`` frames wait, drop the oldest for the new one instead of waiting (the reader then
            keeps up with the source, and the frames handed out are never more than ``most`` behind it); a dropped
            frame comes in its group, before the frames after it, as ``(index, None)``. The segmenter then runs in
            the caller's thread on the frames kept (segmenting frames that may be dropped would take the fit's
            time for nothing).
    """
    if isinstance(most, bool) or not isinstance(most, int) or most < 1:
        raise ConfigError(f"most: expected an int >= 1, got {most!r}")
    waiting: queue.Queue = queue.Queue(maxsize=most)
    stop = threading.Event()
    dropped: list[int] = []  # indices dropped since the caller's last group, oldest first
    lock = threading.Lock()

    def put(item) -> bool:  # False once the caller stopped
        dropping = drop_oldest and not isinstance(item, _End)  # the end comes after every frame: it waits
        while not stop.is_set():
            try:
                waiting.put(item, block=not dropping, timeout=None if dropping else 0.1)
                return True
            except queue.Full:
                if dropping:
                    with lock:
                        try:
                            dropped.append(waiting.get_nowait()[0])
                        except queue.Empty:
                            pass
                continue
        return False

    segment_here = segmenter is not None and not drop_oldest  # a frame that may be dropped is segmented once kept

    def read() -> None:
        try:
            for i, frame in enumerate(frames):
                if stop.is_set() or not put((i, segmenter(frame, frame_index=i) if segment_here else frame)):
                    return
            put(_End())
        except BaseException as error:  # noqa: BLE001 - handed to the caller's thread, raised there
            put(_End(error))

    reader = threading.Thread(target=read, name="arrived_frames", daemon=True)
    reader.start()
    try:
        while True:
            group = [waiting.get()]
            with lock:
                while len(group) < most and not isinstance(group[-1], _End):
                    try:
                        group.append(waiting.get_nowait())
                    except queue.Empty:
                        break
                lost, dropped[:] = [(i, None) for i in dropped], []
            end = group.pop() if isinstance(group[-1], _End) else None
            if segmenter is not None and not segment_here:
                group = [(i, segmenter(frame, frame_index=i)) for i, frame in group]
            # a frame dropped while this group's first was taken is newer than it: in index order
            group = sorted(lost + group, key=lambda pair: pair[0])
            if group:
                yield group
            if end is not None:
                if end.error is not None:
                    raise end.error
                return
    finally:
        stop.set()


def _step_batch(tracker: ShapeTracker, batch: list[tuple[int, np.ndarray]], fps: float | None) -> list[TrackedShape]:
    """``tracker.step_many`` of ``(frame index, mask)`` pairs (nothing for none)."""
    if not batch:
        return []
    indices = [i for i, _ in batch]
    return tracker.step_many([mask for _, mask in batch], frames=indices,
                             times_s=[None if fps is None else i / fps for i in indices])


# ---------------------------------------------------------------------------------------------------------------
# Manipulator pose


#: The warm fit of a tracked manipulator frame: one start from the previous pose, 15 Adam iterations at a working
#: side of 480 px, then 5 Gauss-Newton polish steps, without the appearance term (as the single-image default).
#: Measured on tuning videos (toy arm and Panda, seeds 11-13, fixed and orbiting camera, noisy masks;
#: docs/tracking.md): 30 iterations with the appearance term (the first default) were 0.34 s a frame on Panda and
#: no more accurate; 8 were as accurate there but left more of a 2-4 % depth jump (tests/test_track.py). The side
#: was 320 px until session 32: on the shipped network's masks (a steady outline bias, where carrying the last
#: depth does not average the error out) 480 px cut the tracked end effector's 3D error by 36-60 % on tuning videos,
#: and about as much or less on alternating noise (docs/tracking.md, "The warm fit's working side"). Since session 33
#: the mask term targets each working pixel's coverage (``PoseFitConfig.coverage_target``): on 14 tuning videos
#: (toy arm, Panda, UR5, Baxter) the tracked error went down on 7 and up on 5 (docs/tracking.md, "The mask's
#: coverage as the target of warm fits"). ``dataclasses.replace(WARM_POSE_FIT, outline_polish_loss=0.08)`` (``track
#: pose --warm-outline-polish auto``, not the default) ends a frame whose hull answer the visual meshes find poorly
#: explained with 5 Gauss-Newton steps drawn with the meshes, its boundary offset fitted: nearer on noisy masks at
#: 1.6-3.6x a noisy frame's time (docs/tracking.md, "Warm frames polished with the visual meshes where they ask").
#: ``dataclasses.replace(WARM_POSE_FIT, offset_polish_loss=0.08)`` (``track pose --warm-boundary-offset auto``, not
#: the default) fits the outline's offset in the hulls' own polish where the meshes find the answer poorly
#: explained, for 1.2-1.5x the time: nearer on UR5's and Baxter's noisy videos, farther on Panda's and Z1's reported
#: ones and on the shipped network's tuning videos (docs/tracking.md, "The warm frames' boundary offset in the
#: hulls' polish").
WARM_POSE_FIT = PoseFitConfig(
    iterations=15, working_max_side=480, starts=1, candidates=1, retries=0, polish_newton_steps=5, polish_rounds=0,
    weight_appearance=0.0, coverage_target=True,
    stages=(PoseStage(fraction=1.0, scale=1.0, keep=1, sigma_px2=0.5, lr_scale=0.3, final_lr_factor=0.1),),
)


def calm_pose_fit(warm_fit: PoseFitConfig = WARM_POSE_FIT, iterations: int = 5) -> PoseFitConfig:
    """``warm_fit`` made calm (``PoseTrackConfig.calm_fit``): ``iterations`` Adam steps at 0.03 of ``lr_pose``
    decaying to half of that, then ``warm_fit``'s own polish. On noisy masks the Gauss-Newton polish does the
    fitting and Adam's steps let the outline's noise pull the pose; at this rate they barely move it (session 61's
    tuning videos, ``docs/tracking.md``). It follows a jump less well (``benchmarks/warm_pose_jumps.py``): the
    tracker runs ``warm_fit`` too where its loss is high."""
    if len(warm_fit.stages) != 1:
        raise ConfigError(f"calm_pose_fit: expected a warm fit of one stage (as WARM_POSE_FIT), got "
                          f"{len(warm_fit.stages)}")
    (stage,) = warm_fit.stages
    return replace(warm_fit, iterations=iterations,
                   stages=(replace(stage, lr_scale=0.03, final_lr_factor=0.5),))


def smoothed_pose(recent: Sequence[tuple[int, np.ndarray]]) -> np.ndarray:
    """A moving camera's ``T_cam_root`` at the newest of ``recent`` tracked frames, read off straight lines in time
    through them all: the camera's motion taken as steady over the window (``PoseTrackConfig.smooth_window``).

    Each pose is written about the newest one's, ``R_k = exp(phi_k) R_n`` (``phi_k`` a rotation vector in the camera
    frame) and ``t_k``; a least-squares line in the frame index through the ``phi_k``, and one through the ``t_k``,
    is read at the newest frame ``f_n``: ``R = exp(phi(f_n)) R_n``, ``t = t(f_n)``. Errors that change from frame to
    frame (a segmenter's outline, too wide on one frame and too narrow on the next, moves a single frame's depth by
    centimetres) average out; a steady motion of the camera is followed without lag. Causal: no later frame is
    waited for.

    Args:
        recent: ``(frame index, (4, 4) T_cam_root)`` pairs, oldest first, frame indices increasing.

    Returns:
        ``(4, 4)``; the newest pose itself with fewer than three frames.

    Raises:
        ShapeError: no pose, a pose not ``(4, 4)`` and finite, frame indices not increasing.
    """
    if len(recent) == 0:
        raise ShapeError("recent: expected at least one (frame, T_cam_root) pair")
    frames = np.array([f for f, _ in recent], dtype=np.float64)
    if any(np.shape(T) != (4, 4) for _, T in recent):
        raise ShapeError("recent: expected finite (4, 4) poses")
    poses = np.stack([np.asarray(T, dtype=np.float64) for _, T in recent])  # (F, 4, 4)
    if not np.isfinite(poses).all():
        raise ShapeError("recent: expected finite (4, 4) poses")
    if (np.diff(frames) <= 0).any():
        raise ShapeError(f"recent: expected increasing frame indices, got {frames.astype(int).tolist()}")
    newest = poses[-1]
    if len(recent) < 3:
        return newest
    R_n = torch.from_numpy(newest[:3, :3])
    phi = rotmat_to_rotvec(torch.from_numpy(poses[:, :3, :3]) @ R_n.T).numpy()  # (F, 3)
    s = frames - frames[-1]  # the newest at 0: the lines' intercepts are the answer
    A = np.stack([np.ones_like(s), s], axis=1)  # (F, 2)
    intercepts = np.linalg.lstsq(A, np.concatenate([phi, poses[:, :3, 3]], axis=1), rcond=None)[0][0]  # (6,)
    out = np.eye(4)
    out[:3, :3] = (rotvec_to_rotmat(torch.from_numpy(intercepts[None, :3]))[0] @ R_n).numpy()
    out[:3, 3] = intercepts[3:]
    return out


@dataclass(frozen=True, kw_only=True)
class PoseTrackConfig:
    """Settings of :class:`PoseTracker`.

    Fields:
        full_fit: the fit of the first frame and of re-initialised frames (``estimate_pose``'s defaults).
        warm_fit: the fit of every other frame, started from the last ``T_cam_root`` alone (its starts,
            candidates and retries are not used).
        reinit_ratio: a warm frame whose loss is above this times the running loss is fitted again with
            ``full_fit``, and the pose with the lower loss under ``warm_fit``'s settings kept (the full fit's own
            loss is at its own resolution and target; > 1).
        running_weight: weight of the newest warm fit's loss in the running loss, in (0, 1]. The running loss
            averages the warm fits' own losses only (a full fit's loss is at its own working resolution, which
            may differ: losses at a coarser resolution are higher, and would trigger re-initialisations), and
            only those of frames that were not re-initialised: a bad frame (a wrong mask, a lost track) does not
            raise the level the next frames are held to, so a track lost on it is fitted afresh on the next
            frames until one comes back to that level.
        reinit_limit: after this many re-initialised frames in a row, the running loss (and its lowest, see
            ``drift_ratio``) restarts at the last warm fit's loss (the masks have changed for good, e.g. the robot
            partly out of view; >= 1).
        drift_ratio: a warm frame under ``reinit_ratio`` whose running loss, with its own loss in it, is above
            this times the lowest running loss since the track last started is fitted again with ``full_fit``
            too: a track that starts in a wrong pose and gets worse slowly, each frame a little above the last,
            raises its running loss with it and never jumps above ``reinit_ratio`` times it. When the full fit
            scores lower (under ``warm_fit``'s settings) the running loss and its lowest restart at the full
            fit's loss; when it does not, the higher level is real and accepted (the lowest restarts at the
            running loss). ``None``: off (> 1).
        static_camera: the camera does not move relative to the robot's root: the tracker keeps each tracked
            frame's mask (bit-packed, ``H * W / 8`` bytes), joint readings and pose, and
            :meth:`PoseTracker.static_estimate` refines one ``T_cam_root`` over them with these settings
            (``refine_static_camera``). ``None``: nothing kept.
        running_static: with ``static_camera``, a running estimate too, refined from the frames tracked so far
            with these settings once ``running_static_first`` frames are tracked and again each time their number
            doubles (8, 16, 32, ...: the work grows with the logarithm of the frames), started from the last
            running estimate and the two newest frames' own poses; each :class:`TrackedPose` carries the latest
            (``TrackedPose.static``); the final estimate does not start from it. ``None``: none.
        running_static_first: see ``running_static`` (>= 1).
        calm_fit: a calmer fit tried first on every warm frame (:func:`calm_pose_fit`); where its loss is above
            ``calm_ratio`` times the running loss, ``warm_fit`` runs too, from the same start, and the lower
            loss of the two goes on (then the ``reinit_ratio`` check); before there is a running loss, ``warm_fit``
            alone. ``None``: ``warm_fit`` alone (the default: at ``calm_ratio`` 1.2 nearer on every tuning video
            of the toy arm and on Panda's, but on the reported videos nearer on Panda and Z1, farther on UR5 and
            Baxter, and 27-49 % of frames fell back, so no faster over a video; ``docs/tracking.md``).
        calm_ratio: see ``calm_fit`` (> 1).
        smooth_window: each :class:`TrackedPose` also carries ``smoothed``, :func:`smoothed_pose` of the last this
            many tracked frames (itself among them; fewer at the start, and after a re-initialisation that took the
            full fit: the window starts again there), for a moving camera (>= 2). ``None``: none.
        carry_moments: True (the default since session 71): each warm (and calm) fit's Adam begins with the state
            the last estimate's fit ended with (``PoseResult.moments``), as ``ShapeTrackConfig.carry_moments``;
            nearer in 2D on every tuning video, fixed or orbiting camera (``docs/tracking.md``). False: Adam's
            zeros, the default before.
    """

    full_fit: PoseFitConfig = PoseFitConfig()
    warm_fit: PoseFitConfig = WARM_POSE_FIT
    reinit_ratio: float = 3.0
    running_weight: float = 0.3
    reinit_limit: int = 10
    drift_ratio: float | None = 3.0
    static_camera: StaticCameraConfig | None = None
    running_static: StaticCameraConfig | None = None
    running_static_first: int = 8
    smooth_window: int | None = None
    calm_fit: PoseFitConfig | None = None
    calm_ratio: float = 1.2
    carry_moments: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.carry_moments, bool):
            raise ConfigError(f"carry_moments: expected True or False, got {self.carry_moments!r}")
        for name in ("full_fit", "warm_fit"):
            if not isinstance(getattr(self, name), PoseFitConfig):
                raise ConfigError(f"{name}: expected a PoseFitConfig, got {type(getattr(self, name)).__name__}")
        if self.calm_fit is not None and not isinstance(self.calm_fit, PoseFitConfig):
            raise ConfigError(f"calm_fit: expected a PoseFitConfig or None, got {type(self.calm_fit).__name__}")
        if not (float(self.calm_ratio) > 1.0 and math.isfinite(float(self.calm_ratio))):
            raise ConfigError(f"calm_ratio: expected a finite number > 1, got {self.calm_ratio!r}")
        if not (float(self.reinit_ratio) > 1.0 and math.isfinite(float(self.reinit_ratio))):
            raise ConfigError(f"reinit_ratio: expected a finite number > 1, got {self.reinit_ratio!r}")
        if not 0.0 < float(self.running_weight) <= 1.0:
            raise ConfigError(f"running_weight: expected a number in (0, 1], got {self.running_weight!r}")
        if isinstance(self.reinit_limit, bool) or not isinstance(self.reinit_limit, int) or self.reinit_limit < 1:
            raise ConfigError(f"reinit_limit: expected an int >= 1, got {self.reinit_limit!r}")
        _check_drift_ratio(self.drift_ratio)
        for name in ("static_camera", "running_static"):
            value = getattr(self, name)
            if value is not None and not isinstance(value, StaticCameraConfig):
                raise ConfigError(f"{name}: expected a StaticCameraConfig or None, got {type(value).__name__}")
        if self.running_static is not None and self.static_camera is None:
            raise ConfigError("running_static: needs static_camera (the camera must be fixed relative to the root)")
        first = self.running_static_first
        if isinstance(first, bool) or not isinstance(first, int) or first < 1:
            raise ConfigError(f"running_static_first: expected an int >= 1, got {first!r}")
        window = self.smooth_window
        if window is not None and (isinstance(window, bool) or not isinstance(window, int) or window < 2):
            raise ConfigError(f"smooth_window: expected an int >= 2 or None, got {window!r}")


class _PackedMasks(Sequence):
    """Bit-packed ``(H, W)`` masks read as a sequence of bool arrays, each unpacked when indexed."""

    def __init__(self, packed: list[np.ndarray], shape: tuple[int, int]) -> None:
        self.packed, self.shape = packed, shape

    def __len__(self) -> int:
        return len(self.packed)

    def __getitem__(self, i: int) -> np.ndarray:
        return np.unpackbits(self.packed[i], count=self.shape[0] * self.shape[1]).reshape(self.shape).astype(bool)


#: ``PoseTrackConfig.running_static``'s settings from ``track pose --static-camera``: 40 Adam steps from the
#: last running estimate and the two newest frames' poses (3 candidates), the polish as the final refinement's.
RUNNING_STATIC = StaticCameraConfig(iterations=40, candidates=3)


@dataclass(frozen=True)
class RunningStatic:
    """A fixed camera's running ``T_cam_root`` as one frame left it (``PoseTrackConfig.running_static``).

    Fields:
        T_cam_root: ``(4, 4)`` the latest running estimate, or ``None`` before the first refinement.
        frames: how many tracked frames that estimate was refined from (0 before the first).
        seconds: wall time of the refinement done at this frame (0 at frames without one; not in
            ``TrackedPose.seconds``).
    """

    T_cam_root: np.ndarray | None
    frames: int
    seconds: float


@dataclass(frozen=True, kw_only=True)
class TrackedPose:
    """One frame's outcome (fields as :class:`TrackedShape`'s; ``result`` is a ``PoseResult``; ``static``: the
    running static-camera estimate after this frame, ``None`` without ``PoseTrackConfig.running_static``;
    ``smoothed``: the ``(4, 4)`` smoothed ``T_cam_root`` of a moving camera (``PoseTrackConfig.smooth_window``),
    ``None`` on a skipped frame or without it; ``smooth_frames``: the tracked frames it was read from, ``0`` on a
    skipped frame, ``None`` without ``smooth_window``)."""

    frame: int
    time_s: float | None
    result: PoseResult | None
    reinitialised: bool
    skipped: str | None
    iterations: int
    seconds: float
    static: RunningStatic | None = None
    smoothed: np.ndarray | None = None
    smooth_frames: int | None = None

    def to_dict(self) -> dict:
        """The frame's JSON line: ``T_cam_root`` (4x4, or ``None`` when skipped), loss, ``depth_std_m``
        (``PoseResult.depth_std_m``; ``None`` when skipped or not estimated), timing and flags; with a running
        static estimate also ``static_T_cam_root`` (``None`` before the first), ``static_frames`` and
        ``static_seconds`` (:class:`RunningStatic`); with smoothing ``smooth_T_cam_root`` (``None`` when skipped)
        and ``smooth_frames``."""
        r = self.result
        running = {} if self.static is None else {
            "static_T_cam_root": self.static.T_cam_root, "static_frames": self.static.frames,
            "static_seconds": self.static.seconds}
        if self.smooth_frames is not None:
            running.update(smooth_T_cam_root=self.smoothed, smooth_frames=self.smooth_frames)
        return {
            "frame": self.frame,
            "time_s": self.time_s,
            "T_cam_root": None if r is None else r.T_cam_root,
            "loss": None if r is None else r.loss,
            "depth_std_m": None if r is None or not math.isfinite(r.depth_std_m) else r.depth_std_m,
            "iterations": self.iterations,
            "seconds": self.seconds,
            "reinitialised": self.reinitialised,
            "skipped": self.skipped,
            **running,
        }


class PoseTracker(_RunningLoss):
    """Tracks a manipulator's camera-to-root pose through one video, frame by frame: a full fit first, then fits
    warm-started from the previous pose (the camera may move slowly), a full fit again when the loss jumps."""

    def __init__(self, model: ManipulatorModel, camera: Camera, config: PoseTrackConfig = PoseTrackConfig()) -> None:
        if not isinstance(config, PoseTrackConfig):
            raise ConfigError(f"config: expected a PoseTrackConfig, got {type(config).__name__}")
        self.model = model
        self.camera = camera
        self.config = config
        self.last: PoseResult | None = None
        self.running_loss: float | None = None
        self.lowest_running_loss: float | None = None  # since the running loss last (re)started: drift_ratio
        self.reinitialisations = 0
        self.drift_reinitialisations = 0  # of those, the ones drift_ratio triggered
        self.reinitialised_in_a_row = 0
        self.batch_retries = 0  # batch frames fitted again on their own (``config.batch_retry_ratio``)
        self.skipped = 0
        self.calm_fallbacks = 0  # warm frames whose calm fit's loss was high (``config.calm_fit``)
        # (frame, packed mask, joint readings, T_cam_root) of the tracked frames, with config.static_camera
        self.kept: list[tuple[int, np.ndarray, torch.Tensor, np.ndarray]] | None = (
            None if config.static_camera is None else [])
        self.running: StaticCameraResult | None = None  # the latest running estimate (config.running_static)
        self.running_frames = 0  # the tracked frames it was refined from
        self.running_seconds = 0.0  # all its refinements' wall time
        self._next_running = config.running_static_first
        self.recent: list[tuple[int, np.ndarray]] = []  # (frame, T_cam_root) of the smoothing window

    def step(self, mask: np.ndarray, joint_angles: torch.Tensor, *, frame: int, time_s: float | None = None
             ) -> TrackedPose:
        """Fit one frame's ``(H, W)`` bool mask with its ``(J,)`` joint readings (order of
        ``model.joint_names``). An empty mask gives a skipped frame; other bad input raises."""
        t0 = time.perf_counter()
        config = self.config
        reinitialised = False
        try:
            if self.last is None:
                result = estimate_pose(mask, self.model, joint_angles, self.camera, config.full_fit)
                iterations = result.iterations
            else:
                result, iterations = self._warm_fit(mask, joint_angles)
                warm_loss = result.loss
                jumped, drifted = self._level_check(warm_loss, frame)
                if jumped or drifted:
                    full = estimate_pose(mask, self.model, joint_angles, self.camera, config.full_fit)
                    iterations += full.iterations
                    reinitialised = True
                    self.reinitialisations += 1
                    full_loss = self._warm_loss(mask, joint_angles, full)
                    took_full = full_loss < self._warm_loss(mask, joint_angles, result)
                    result = full if took_full else result
        except ShapeError as error:
            if "mask" not in str(error):
                raise
            log.warning("frame %d skipped: %s", frame, error)
            return self.skip(reason=str(error), frame=frame, time_s=time_s, seconds=time.perf_counter() - t0)
        if self.last is not None:  # see PoseTrackConfig.running_weight, reinit_limit and drift_ratio
            self.reinitialised_in_a_row = self.reinitialised_in_a_row + 1 if reinitialised else 0
            if self.running_loss is None or self.reinitialised_in_a_row >= config.reinit_limit:
                self._restart_running_loss(warm_loss)
            elif drifted:
                self._restart_running_loss(full_loss if took_full else self._running_with(warm_loss))
            elif not reinitialised:
                self.running_loss = self._running_with(warm_loss)
                self.lowest_running_loss = min(self.lowest_running_loss, self.running_loss)
        self.last = result
        seconds = time.perf_counter() - t0
        static = None
        if self.kept is not None:
            self.kept.append((frame, np.packbits(mask), joint_angles, result.T_cam_root))
            static = self._run_static()
        smoothed, smooth_frames = None, None
        if config.smooth_window is not None:  # the window starts again where a full fit replaced the warm one
            restart = reinitialised and took_full
            self.recent = [*([] if restart else self.recent[-(config.smooth_window - 1):]), (frame, result.T_cam_root)]
            smoothed, smooth_frames = smoothed_pose(self.recent), len(self.recent)
        return TrackedPose(frame=frame, time_s=time_s, result=result, reinitialised=reinitialised, skipped=None,
                           iterations=iterations, seconds=seconds, static=static, smoothed=smoothed,
                           smooth_frames=smooth_frames)

    def _warm_fit(self, mask: np.ndarray, joint_angles: torch.Tensor) -> tuple[PoseResult, int]:
        """A warm frame's fit from the last pose: the calm fit where it does (``PoseTrackConfig.calm_fit``), else
        the warm fit too and the lower loss; with the iterations of both."""
        config = self.config
        calm = None
        if config.calm_fit is not None and self.running_loss is not None:
            calm = estimate_pose(mask, self.model, joint_angles, self.camera, config.calm_fit,
                                 initial_T_cam_root=self.last.T_cam_root, initial_moments=self._moments())
            if calm.loss <= config.calm_ratio * self.running_loss:
                return calm, calm.iterations
            self.calm_fallbacks += 1
        result = estimate_pose(mask, self.model, joint_angles, self.camera, config.warm_fit,
                               initial_T_cam_root=self.last.T_cam_root, initial_moments=self._moments())
        if calm is None:
            return result, result.iterations
        return (calm if calm.loss < result.loss else result), calm.iterations + result.iterations

    def _masks(self) -> Sequence[np.ndarray]:
        """The kept frames' masks, each unpacked when asked for: a refinement reads at most
        ``StaticCameraConfig.max_frames`` of them."""
        return _PackedMasks([packed for _, packed, _, _ in self.kept], self.camera.image_size)

    def _run_static(self) -> RunningStatic | None:
        """The running static estimate after the newest kept frame, refined now when its turn has come
        (``PoseTrackConfig.running_static``)."""
        config = self.config
        if config.running_static is None:
            return None
        seconds = 0.0
        if len(self.kept) >= self._next_running:
            starts = ([] if self.running is None else [self.running.T_cam_root]) + [T for *_, T in self.kept[-2:]]
            self.running = refine_static_camera(self._masks(), [q for _, _, q, _ in self.kept], self.model,
                                                self.camera, starts, config.running_static)
            seconds = self.running.seconds
            self.running_seconds += seconds
            self.running_frames = len(self.kept)
            self._next_running *= 2
        return self._running_snapshot(seconds)

    def _running_snapshot(self, seconds: float) -> RunningStatic:
        return RunningStatic(T_cam_root=None if self.running is None else self.running.T_cam_root,
                             frames=self.running_frames, seconds=seconds)

    def static_estimate(self) -> StaticCameraResult:
        """One ``T_cam_root`` refined over every tracked frame (``PoseTrackConfig.static_camera``), started from
        the frames' own poses (``refine_static_camera``; indices in the result count the tracked frames,
        :attr:`kept` names them). Not from the running estimate: started there too, it ended farther on two of three
        tuning videos (``docs/tracking.md``).

        Raises:
            ConfigError: no ``static_camera`` in the config, or no frame tracked.
        """
        if self.kept is None:
            raise ConfigError("static_estimate: the tracker keeps no frames (PoseTrackConfig.static_camera is None)")
        if not self.kept:
            raise ConfigError("static camera: no frame was tracked, nothing to refine")
        return refine_static_camera(self._masks(), [q for _, _, q, _ in self.kept], self.model, self.camera,
                                    [T for *_, T in self.kept], self.config.static_camera)

    def _restart_running_loss(self, loss: float) -> None:
        """Start the running loss, and its lowest, at ``loss``; the re-initialisations in a row start again."""
        self.running_loss = self.lowest_running_loss = loss
        self.reinitialised_in_a_row = 0

    def _warm_loss(self, mask: np.ndarray, joint_angles: torch.Tensor, result: PoseResult) -> float:
        """The loss of ``result``'s pose under the warm fit's settings: a full fit's own loss is at its own
        working resolution and target (``PoseFitConfig.coverage_target``), so a re-initialised frame compares the
        two fits' poses on this one scale."""
        return pose_loss_at(mask, self.model, joint_angles, self.camera, result.T_cam_root, self.config.warm_fit)

    def skip(self, *, reason: str, frame: int, time_s: float | None = None, seconds: float = 0.0) -> TrackedPose:
        """Record a frame without an estimate (e.g. one the video reader could not decode); tracking goes on from
        the last estimate."""
        if not isinstance(reason, str) or not reason:
            raise ConfigError(f"reason: expected a non-empty string, got {reason!r}")
        self.skipped += 1
        static = None if self.config.running_static is None else self._running_snapshot(0.0)  # fields kept
        return TrackedPose(frame=frame, time_s=time_s, result=None, reinitialised=False, skipped=reason,
                           iterations=0, seconds=seconds, static=static,
                           smooth_frames=None if self.config.smooth_window is None else 0)


def track_pose(
    frames: Iterable[np.ndarray],
    model: ManipulatorModel,
    joint_readings: Iterable[torch.Tensor],
    camera: Camera,
    config: PoseTrackConfig = PoseTrackConfig(),
    *,
    segmenter: Callable[..., np.ndarray] | None = None,
    fps: float | None = None,
) -> Iterator[TrackedPose]:
    """Track a manipulator's ``T_cam_root`` through ``frames``, yielding each frame's outcome as soon as it is done.

    Args:
        frames: any iterable of ``(H, W)`` bool masks, or of BGR images when ``segmenter`` is given.
        model: the robot (``pipeline.robots.load_robot``).
        joint_readings: one ``(J,)`` tensor per frame (order of ``model.joint_names``; ``model.joint_vector``
            turns readings by name into one), consumed alongside ``frames``.
        camera: the camera (fixed intrinsics; it may move relative to the robot).
        config: tracking settings.
        segmenter: ``segmenter(image, frame_index=i) -> mask``, or ``None`` meaning *the frames are masks*.
        fps: frame rate for ``time_s``; ``None`` meaning *unknown*.

    Raises:
        ConfigError: fewer joint readings than frames (the message names the first frame without one).
    """
    if fps is not None:
        check_positive(fps, "fps")
    tracker = PoseTracker(model, camera, config)
    readings = iter(joint_readings)
    for i, frame in enumerate(frames):
        q = next(readings, None)
        if q is None:
            raise ConfigError(f"joint_readings: no reading for frame {i} (one (J,) tensor per frame expected)")
        mask = frame if segmenter is None else segmenter(frame, frame_index=i)
        yield tracker.step(mask, q, frame=i, time_s=None if fps is None else i / fps)
