"""Synthetic test cases for the camera-to-robot pose fit: a random view of a manipulator through a given camera,
its exact mask, and segmenter-like corruptions of it (a wobbly boundary, a false-positive blob, lens distortion).

Random joints, in-view camera poses and shaded images come from :mod:`pipeline.synth.manipulator`; this module
fixes the camera (the pose fit's input) and adds the mask corruptions.

Convention: camera frame OpenCV (x right, y down, z forward), metres; ``T_cam_root`` maps root-frame points to the
camera (``p_cam = T_cam_root @ p_root``); pixels ``(u, v)`` = (column, row), pixel centres at integers; masks
``(H, W)`` bool; images ``(H, W, 3)`` uint8 BGR. All randomness comes from the ``numpy.random.Generator`` passed
in, so a seed reproduces a case exactly. Arrays are numpy float64 (test data, outside autograd).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch

from pipeline.camera import Camera
from pipeline.checks import check_positive
from pipeline.errors import ShapeError
from pipeline.preprocess import check_mask, exact_distance_transform
from pipeline.render import render_hard
from pipeline.robots.manipulator import ManipulatorModel
from pipeline.synth.manipulator import (
    random_background,
    random_camera_pose,
    random_colors,
    random_joint_angles,
    random_lighting,
    render_mesh_image,
)

__all__ = ["random_view", "render_robot_mask", "painter_mask", "coverage_mask", "render_robot_image", "corrupt_mask",
           "distort_image", "manipulator_sequence"]


def random_view(
    model: ManipulatorModel,
    camera: Camera,
    generator: np.random.Generator,
    *,
    fill_range: tuple[float, float] = (0.45, 0.9),
) -> tuple[np.ndarray, np.ndarray]:
    """Random joint values (uniform within the URDF limits) and a random camera pose that sees the whole robot.

    See ``pipeline.synth.manipulator.random_camera_pose`` for the viewpoints (any azimuth, elevation -20 to 70
    degrees about the root's z axis, some roll) and ``fill_range`` (the robot's bounding-sphere diameter over the
    image's short side).

    Returns:
        ``(joint_angles (J,), T_cam_root (4, 4))``, rad or m, metres.
    """
    q = random_joint_angles(model, generator)
    verts_root = model.mesh_in_root(torch.from_numpy(q)[None])[0].numpy()  # (V, 3)
    T_cam_root = random_camera_pose(verts_root, camera.K_array(), camera.image_size, generator, fill_range=fill_range)
    return q, T_cam_root


def render_robot_mask(
    model: ManipulatorModel, joint_angles: np.ndarray, T_cam_root: np.ndarray, camera: Camera
) -> np.ndarray:
    """The robot's exact silhouette (``pipeline.render.render_hard``) through the camera without its distortion.

    Args:
        joint_angles: ``(J,)`` rad or m.
        T_cam_root: ``(4, 4)`` metres.

    Returns:
        ``(H, W)`` bool, the camera's size.
    """
    return render_hard(_verts_cam(model, joint_angles, T_cam_root)[None], model.faces, camera.K_tensor(),
                       camera.image_size)[0].numpy()


def painter_mask(model: ManipulatorModel, q: np.ndarray, T_cam_root: np.ndarray, camera: Camera,
                 skip_links: tuple[str, ...] = ()) -> np.ndarray:
    """The robot's silhouette by supersampled coverage, a renderer independent of the fit's: vertices projected by
    ``cv2.projectPoints`` (lens distortion included), every projected triangle tested at 8 x 8 sample points per
    pixel (:func:`coverage_mask`); a pixel is robot where at least half its samples are inside some triangle.

    (Until 2026-11-24 the triangles were filled with OpenCV's ``fillConvexPoly`` at 8x, which fills every sample an
    edge touches: the masks were 0.3-0.5 % too large, all of it on the outline, enough to move a CAD fit's depth by
    about 5 mm at 2 m; docs/any-manipulator.md.)"""
    verts = model.mesh_in_root(torch.from_numpy(q)[None])[0].numpy()  # (V, 3) root frame
    keep = np.ones(len(model.faces), dtype=bool)
    for name in skip_links:
        keep &= (model.vert_link_index[model.faces[:, 0]] != model.link_names.index(name)).numpy()
    verts_cam = verts @ T_cam_root[:3, :3].T + T_cam_root[:3, 3]
    faces = model.faces.numpy()[keep]
    faces = faces[(verts_cam[faces][:, :, 2] > 1e-3).all(axis=1)]  # triangles in front of the camera
    pixels, _ = cv2.projectPoints(verts_cam, np.zeros(3), np.zeros(3), camera.K_array(), camera.dist_array())
    return coverage_mask(pixels[:, 0].astype(np.float64)[faces], camera.image_size)


def coverage_mask(triangles: np.ndarray, image_size: tuple[int, int], samples: int = 8,
                  chunk: int = 4_000_000) -> np.ndarray:
    """Pixels at least half covered by a union of triangles, by point sampling.

    Args:
        triangles: ``(F, 3, 2)`` corners in pixels (pixel centres at integers).
        image_size: ``(H, W)``.
        samples: sample points per pixel side, at ``u - 1/2 + (s + 1/2) / samples``; a sample on an edge counts.
        chunk: sample tests per vectorised batch (memory bound).

    Returns:
        ``(H, W)`` bool: at least ``samples**2 / 2`` of the pixel's samples inside some triangle.
    """
    H, W = image_size
    n = samples
    tri = np.array(triangles, dtype=np.float64).reshape(-1, 3, 2)
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    drawn = np.isfinite(area2) & (np.abs(area2) > 1e-12)
    tri, area2 = tri[drawn], area2[drawn]
    tri[area2 < 0] = tri[area2 < 0][:, [0, 2, 1]]  # one orientation: every edge function >= 0 inside
    offset = (n - 1) / 2.0  # sample index x = n u + s sits at (x - offset) / n pixels
    lo = np.maximum(np.ceil(np.clip(tri.min(axis=1) * n + offset, -1.0, n * max(H, W) + 1.0)), 0).astype(np.int64)
    hi = np.floor(np.clip(tri.max(axis=1) * n + offset, -1.0, n * max(H, W) + 1.0)).astype(np.int64)
    hi = np.minimum(hi, np.array([n * W - 1, n * H - 1]))
    inside_image = (hi >= lo).all(axis=1)
    tri, lo, hi = tri[inside_image], lo[inside_image], hi[inside_image]
    span = (hi - lo + 1).max(axis=1, initial=0)
    canvas = np.zeros((n * H, n * W), dtype=bool)
    size, smaller = 4, 0
    while len(tri) and smaller <= span.max():  # size classes of the bounding box: 4, 8, 16, ... samples
        group = np.nonzero((span > smaller) & (span <= size))[0]
        if size * size <= chunk:  # many triangles at once, each on a size x size grid from its box's corner
            grid = np.arange(size)
            step = chunk // (size * size)
            for k in range(0, len(group), step):
                idx = group[k : k + step]
                X = lo[idx, 0, None, None] + grid[None, None, :]  # (T, 1, S)
                Y = lo[idx, 1, None, None] + grid[None, :, None]  # (T, S, 1)
                inside = (X <= hi[idx, 0, None, None]) & (Y <= hi[idx, 1, None, None])
                inside &= _inside_triangles(tri[idx][:, None, None], (X - offset) / n, (Y - offset) / n)
                t, i, j = np.nonzero(inside)
                canvas[lo[idx[t], 1] + i, lo[idx[t], 0] + j] = True
        else:  # large triangles one by one, in bands of rows
            for t in group:
                (x0, y0), (x1, y1) = lo[t], hi[t]
                X = np.arange(x0, x1 + 1)[None, :]
                rows = max(1, chunk // (x1 - x0 + 1))
                for r in range(y0, y1 + 1, rows):
                    Y = np.arange(r, min(r + rows, y1 + 1))[:, None]
                    canvas[r : r + len(Y), x0 : x1 + 1] |= _inside_triangles(tri[t], (X - offset) / n, (Y - offset) / n)
        smaller, size = size, size * 2
    return canvas.reshape(H, n, W, n).sum(axis=(1, 3)) * 2 >= n * n


def _inside_triangles(tri: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Points ``(px, py)`` on or inside triangles ``tri (..., 3, 2)`` of positive orientation (broadcast)."""
    inside = np.ones(np.broadcast_shapes(tri.shape[:-2], px.shape, py.shape), dtype=bool)
    for e in range(3):
        a, b = tri[..., e, :], tri[..., (e + 1) % 3, :]
        inside &= (b[..., 0] - a[..., 0]) * (py - a[..., 1]) - (b[..., 1] - a[..., 1]) * (px - a[..., 0]) >= 0
    return inside


def render_robot_image(
    model: ManipulatorModel,
    joint_angles: np.ndarray,
    T_cam_root: np.ndarray,
    camera: Camera,
    generator: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """A shaded picture of the robot (one random colour per link out of 1-3, random light) on random clutter whose
    colours keep away from the robot's, and its exact mask (``pipeline.synth.manipulator.render_mesh_image``).

    Returns:
        ``(image (H, W, 3) uint8 BGR, mask (H, W) bool)``.
    """
    palette = random_colors(generator, int(generator.integers(1, 4)))
    link_color = palette[generator.integers(0, len(palette), len(model.link_names))]  # (L, 3)
    faces = model.faces.numpy()
    face_colors = link_color[model.vert_link_index.numpy()[faces[:, 0]]]  # (F, 3)
    background = random_background(generator, camera.image_size, palette)
    verts = _verts_cam(model, joint_angles, T_cam_root).numpy()
    return render_mesh_image(verts, faces, face_colors, camera.K_array(), background, random_lighting(generator))


def corrupt_mask(
    mask: np.ndarray,
    generator: np.random.Generator,
    *,
    boundary_noise_px: float = 1.0,
    noise_scale_px: float = 6.0,
    blob_fraction: float = 0.0,
) -> np.ndarray:
    """A segmenter-like corruption of a clean mask: a wobbly boundary and a false-positive blob.

    Boundary: the signed distance to the boundary plus smooth Gaussian noise (standard deviation
    ``boundary_noise_px`` pixels, correlated over ``noise_scale_px``) is thresholded where it keeps the mask's area
    (the level set of its ``area`` highest values), so the boundary moves in and out by about
    ``boundary_noise_px`` without changing the area: thin parts may thin out while others grow, the robot's
    overall image size (its depth) stays unbiased. Blob: a filled ellipse of ``blob_fraction`` times the mask's
    area, at a random place at least 10 px from the robot (none if there is no such place in 50 draws).

    Args:
        mask: ``(H, W)`` bool, not empty.
        boundary_noise_px: boundary noise amplitude, pixels (0 for none).
        noise_scale_px: correlation length of that noise, pixels.
        blob_fraction: area of the false-positive blob relative to the mask's (0 for none).

    Returns:
        ``(H, W)`` bool.
    """
    check_mask(mask)
    check_positive(boundary_noise_px, "boundary_noise_px", allow_zero=True)
    check_positive(noise_scale_px, "noise_scale_px")
    check_positive(blob_fraction, "blob_fraction", allow_zero=True)
    out = mask.copy()
    H, W = mask.shape
    if boundary_noise_px > 0:
        # float32 as OpenCV gave them before, so that the seeded benchmark cases stay as they were
        inside = exact_distance_transform(mask).astype(np.float32)  # >= 1 inside
        outside = exact_distance_transform(~mask).astype(np.float32)  # >= 1 out
        signed = np.where(mask, inside - 0.5, 0.5 - outside)  # the boundary at 0, halfway between pixel centres
        noise = cv2.GaussianBlur(generator.normal(size=(H, W)).astype(np.float32), (0, 0), noise_scale_px)
        noise *= boundary_noise_px / max(float(noise.std()), 1e-12)
        level = (signed + noise).ravel()  # (H*W,)
        keep = np.argpartition(-level, int(mask.sum()) - 1)[: int(mask.sum())]  # the area's worth of highest levels
        out = np.zeros(H * W, bool)
        out[keep] = True
        out = out.reshape(H, W)
    if blob_fraction > 0:
        area = blob_fraction * float(mask.sum())
        far = exact_distance_transform(~out)
        for _ in range(50):
            a = math.sqrt(area / math.pi) * generator.uniform(1.0, 1.8)  # semi-axes a >= b, area pi a b
            b = area / (math.pi * a)
            cu, cv_ = generator.uniform(a, W - 1 - a), generator.uniform(a, H - 1 - a)
            blob = np.zeros((H, W), np.uint8)
            cv2.ellipse(blob, (int(round(cu)), int(round(cv_))), (max(int(round(a)), 1), max(int(round(b)), 1)),
                        generator.uniform(0, 180), 0, 360, 1, -1)
            if blob.any() and far[blob.astype(bool)].min() >= 10:
                out |= blob.astype(bool)
                break
    return out


def distort_image(image: np.ndarray, camera: Camera, *, is_mask: bool = False) -> np.ndarray:
    """What a camera with lens distortion records of an ideal (pinhole) picture: the inverse of
    ``pipeline.camera.undistort_image``.

    Each output pixel is undistorted with the camera's coefficients (``cv2.undistortPoints`` with ``P = K``) and
    samples the ideal picture there: bilinear for images, nearest neighbour for masks (which stay binary); 0 where
    it falls outside.

    Args:
        image: ``(H, W)`` or ``(H, W, C)`` ideal image, or an ``(H, W)`` bool mask with ``is_mask``; the camera's
            size.

    Returns:
        The distorted picture, same shape and dtype.
    """
    if is_mask:
        check_mask(image)
    elif not isinstance(image, np.ndarray) or image.ndim not in (2, 3):
        raise ShapeError(f"image: expected an (H, W) or (H, W, C) array, got {getattr(image, 'shape', image)}")
    H, W = camera.image_size
    if image.shape[:2] != (H, W):
        raise ShapeError(f"image: expected the camera's size ({H}, {W}), got {image.shape[:2]}")
    if not camera.has_distortion:
        return image.copy()
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)[:, None]  # (H*W, 1, 2) distorted pixels
    K = camera.K_array()
    ideal = cv2.undistortPoints(pixels, K, camera.dist_array(), P=K)[:, 0]  # (H*W, 2) where they look in the ideal
    map_x = ideal[:, 0].reshape(H, W).astype(np.float32)
    map_y = ideal[:, 1].reshape(H, W).astype(np.float32)
    if is_mask:
        out = cv2.remap(image.astype(np.uint8), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        return out.astype(bool)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def _verts_cam(model: ManipulatorModel, joint_angles: np.ndarray, T_cam_root: np.ndarray) -> torch.Tensor:
    q = np.asarray(joint_angles, dtype=np.float64)
    if q.shape != (len(model.joint_names),) or not np.isfinite(q).all():
        raise ShapeError(f"joint_angles: expected {len(model.joint_names)} finite values, got shape {q.shape}")
    T = np.asarray(T_cam_root, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ShapeError(f"T_cam_root: expected a finite (4, 4) transform, got shape {T.shape}")
    verts_root = model.mesh_in_root(torch.from_numpy(q)[None])[0]  # (V, 3)
    return verts_root @ torch.from_numpy(T[:3, :3]).T + torch.from_numpy(T[:3, 3])



def manipulator_sequence(
    model: ManipulatorModel,
    camera: Camera,
    generator: np.random.Generator,
    frames: int,
    *,
    orbit_deg_per_frame: float = 0.0,
    period_frames: float = 60.0,
    fill_range: tuple[float, float] = (0.45, 0.6),
    elevation_deg: tuple[float, float] = (0.0, 40.0),
    handheld_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Truth of a synthetic video: a manipulator whose joints move between two random configurations, seen by a
    fixed camera or by one orbiting slowly about the vertical (root z) axis through the robot's centre, steadily
    or, with ``handheld_deg``, swaying as a hand-held camera does.

    The joints follow ``q_k = q_a + (q_b - q_a) (1 - cos(2 pi k / period_frames)) / 2`` (``q_a``, ``q_b`` uniform
    within the limits); the camera pose ``T_k = T_0 @ A_k``, with ``A_k`` a turn of ``k * orbit_deg_per_frame``
    degrees about that axis (0: a static camera); ``T_0`` is a random view (``random_camera_pose``, elevation in
    ``elevation_deg``: side views by default, where a tracking camera usually is) that keeps the robot of every frame
    in the image. ``handheld_deg > 0`` then turns and moves each frame's camera by a sway ``H_k`` (``T_k <- H_k
    @ T_k``, about the camera's centre): each of its three rotation-vector and three translation components is a sum
    of two sines of random periods (15-40 frames) and phases, of amplitude ``handheld_deg / 2`` degrees each (the
    rotation) and ``handheld_deg / 2`` cm (the translation); drawn after everything else, so the same generator
    gives the same joints and ``T_0`` with and without it. The sway may take part of the robot out of the image.

    Returns:
        ``(joint_angles (F, J), T_cam_root (F, 4, 4))``, rad or m, metres.
    """
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise ShapeError(f"frames: expected an int >= 1, got {frames!r}")
    check_positive(period_frames, "period_frames")
    q_a, q_b = random_joint_angles(model, generator), random_joint_angles(model, generator)
    phase = (1.0 - np.cos(2.0 * math.pi * np.arange(frames) / period_frames)) / 2.0  # (F,)
    joints = q_a + phase[:, None] * (q_b - q_a)  # (F, J)
    verts = model.mesh_in_root(torch.from_numpy(joints))  # (F, V, 3)
    verts = verts[:, :: max(1, verts.shape[1] // 400)].numpy()  # a few hundred points per frame are enough
    centre = 0.5 * (verts.reshape(-1, 3).min(axis=0) + verts.reshape(-1, 3).max(axis=0))
    turns = []
    for k in range(frames):
        angle = math.radians(k * orbit_deg_per_frame)
        A = np.eye(4)
        A[:3, :3] = [[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0, 0, 1]]
        A[:3, 3] = centre - A[:3, :3] @ centre  # about the vertical axis through the centre
        turns.append(A)
    seen = np.concatenate([v @ A[:3, :3].T + A[:3, 3] for v, A in zip(verts, turns)])  # every frame's robot
    T_0 = random_camera_pose(seen, camera.K_array(), camera.image_size, generator, fill_range=fill_range,
                             elevation_deg=elevation_deg, margin_px=0.04 * min(camera.image_size))
    poses = np.stack([T_0 @ A for A in turns])
    if handheld_deg:
        check_positive(handheld_deg, "handheld_deg")
        poses = _swayed(poses, generator, handheld_deg)
    return joints, poses


def _swayed(poses: np.ndarray, generator: np.random.Generator, amplitude_deg: float) -> np.ndarray:
    """``poses (F, 4, 4)`` each turned and moved about its camera's centre by a smooth random sway (see
    :func:`manipulator_sequence`'s ``handheld_deg``)."""
    from scipy.spatial.transform import Rotation

    k = np.arange(len(poses), dtype=np.float64)[:, None, None]  # (F, 1, 1)
    periods = generator.uniform(15.0, 40.0, size=(1, 6, 2))
    phases = generator.uniform(0.0, 2.0 * math.pi, size=(1, 6, 2))
    sway = (np.sin(2.0 * math.pi * k / periods + phases) * (amplitude_deg / 2.0)).sum(axis=2)  # (F, 6)
    H = np.tile(np.eye(4), (len(poses), 1, 1))
    H[:, :3, :3] = Rotation.from_rotvec(np.radians(sway[:, :3])).as_matrix()
    H[:, :3, 3] = sway[:, 3:] * 0.01  # centimetres
    return H @ poses
