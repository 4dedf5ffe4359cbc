"""Synthetic images of a URDF manipulator (and of any triangle mesh) with exact masks, domain-randomised.

For segmentation training and tests: random joint angles, a random camera that sees the whole robot, flat-shaded
painter's-algorithm drawing with random lighting over random clutter, then random photometric changes.

Convention: camera frame OpenCV (x right, y down, z forward), metres; the root frame of the robot is z up (URDF
habit) for the choice of viewpoints; pixels ``(u, v)`` = (column, row) with pixel centres at integer coordinates;
images ``(H, W, 3)`` uint8 BGR; masks ``(H, W)`` bool, exactly ``pipeline.render.render_hard``'s silhouette (pixel
centres inside a projected triangle). All randomness comes from the ``numpy.random.Generator`` passed in.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from pipeline.checks import check_image_size
from pipeline.errors import ConfigError, ShapeError
from pipeline.render import render_hard
from pipeline.robots.manipulator import ManipulatorModel

__all__ = [
    "Lighting",
    "ManipulatorImage",
    "random_background",
    "random_camera_pose",
    "random_colors",
    "random_intrinsics",
    "random_joint_angles",
    "random_lighting",
    "random_manipulator_image",
    "randomize_photometric",
    "render_mesh_image",
]

#: Smallest distance in the (a*, b*) plane of 8-bit Lab between a clutter colour and a robot colour: clutter never
#: has the robot's hue and chroma (it may have its lightness, since shading changes that anyway).
MIN_CHROMA_DISTANCE = 22.0


@dataclass(frozen=True, kw_only=True)
class Lighting:
    """One directional light, Blinn-Phong, flat shading per face.

    ``colour = base * (ambient + diffuse * max(0, n.l)) + 255 * specular * max(0, n.h)^shininess``.

    Attributes:
        direction_cam: unit vector towards the light, camera frame.
        ambient, diffuse, specular: weights (>= 0).
        shininess: Blinn-Phong exponent (> 0).
    """

    direction_cam: tuple[float, float, float] = (0.3, -0.5, -0.81)
    ambient: float = 0.35
    diffuse: float = 0.65
    specular: float = 0.0
    shininess: float = 20.0


@dataclass(frozen=True, kw_only=True)
class ManipulatorImage:
    """One synthetic manipulator image and its truth.

    Attributes:
        image: ``(H, W, 3)`` uint8 BGR.
        mask: ``(H, W)`` bool, the robot's exact silhouette.
        joint_angles: ``(J,)`` float64 in the model's ``joint_names`` order, rad or m.
        T_cam_root: ``(4, 4)`` float64 pose of the root frame in the camera frame, metres.
        K: ``(3, 3)`` float64 intrinsics, pixels.
    """

    image: np.ndarray
    mask: np.ndarray
    joint_angles: np.ndarray
    T_cam_root: np.ndarray
    K: np.ndarray


def random_manipulator_image(
    model: ManipulatorModel,
    generator: np.random.Generator,
    image_size: tuple[int, int],
    *,
    fill_range: tuple[float, float] = (0.45, 1.0),
    photometric: bool = True,
) -> ManipulatorImage:
    """A random view of ``model`` at random joint angles, coloured and lit at random on random clutter.

    Each link takes one of 1-3 random colours (saturated, or white/grey/black); the camera has a random
    horizontal field of view of 45-75 degrees and sees the whole robot (see :func:`random_camera_pose`).

    Args:
        model: the manipulator (``pipeline.robots.load_urdf_robot``).
        generator: numpy random generator.
        image_size: ``(H, W)``.
        fill_range: range of the robot's bounding-sphere diameter over the image's short side.
        photometric: apply :func:`randomize_photometric` (colour cast, contrast, gamma, blur, noise, JPEG).
    """
    H, W = check_image_size(image_size)
    q = random_joint_angles(model, generator)
    verts_root = model.mesh_in_root(torch.from_numpy(q)[None])[0].numpy()  # (V, 3)
    faces = model.faces.numpy()
    K = random_intrinsics(generator, (H, W))
    T_cam_root = random_camera_pose(verts_root, K, (H, W), generator, fill_range=fill_range)
    verts_cam = verts_root @ T_cam_root[:3, :3].T + T_cam_root[:3, 3]
    palette = random_colors(generator, int(generator.integers(1, 4)))
    link_color = palette[generator.integers(0, len(palette), len(model.link_names))]  # (L, 3)
    face_colors = link_color[model.vert_link_index.numpy()[faces[:, 0]]]  # (F, 3)
    background = random_background(generator, (H, W), palette)
    image, mask = render_mesh_image(verts_cam, faces, face_colors, K, background, random_lighting(generator))
    if photometric:
        image = randomize_photometric(image, generator)
    return ManipulatorImage(image=image, mask=mask, joint_angles=q, T_cam_root=T_cam_root, K=K)


def random_joint_angles(model: ManipulatorModel, generator: np.random.Generator) -> np.ndarray:
    """``(J,)`` float64 joint values uniform within the URDF limits (``[-pi, pi]`` where a limit is infinite)."""
    lower = np.maximum(model.joint_lower.numpy(), -math.pi)
    upper = np.minimum(model.joint_upper.numpy(), math.pi)
    return generator.uniform(lower, upper)


def random_intrinsics(
    generator: np.random.Generator, image_size: tuple[int, int], hfov_deg: tuple[float, float] = (45.0, 75.0)
) -> np.ndarray:
    """``(3, 3)`` float64 pinhole intrinsics: square pixels, a random horizontal field of view, centred."""
    H, W = check_image_size(image_size)
    f = 0.5 * W / math.tan(math.radians(generator.uniform(*hfov_deg)) / 2.0)
    return np.array([[f, 0.0, (W - 1) / 2.0], [0.0, f, (H - 1) / 2.0], [0.0, 0.0, 1.0]])


def random_camera_pose(
    points_root: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    generator: np.random.Generator,
    *,
    fill_range: tuple[float, float] = (0.45, 1.0),
    elevation_deg: tuple[float, float] = (-20.0, 70.0),
    max_roll_deg: float = 25.0,
    margin_px: float = 2.0,
    max_tries: int = 200,
) -> np.ndarray:
    """A random ``T_cam_root`` ``(4, 4)`` that sees every point, from a random direction above or around them.

    The camera looks at the centre of the points' bounding box from a random azimuth and elevation (about the
    root's z axis), rolled by up to ``max_roll_deg``, at the distance where the bounding sphere's diameter is a
    random fraction (``fill_range``) of the image's short side; then slid parallel to the image plane to a random
    place where every point projects at least ``margin_px`` inside the image.

    Args:
        points_root: ``(N, 3)`` points (e.g. mesh vertices) in the root frame, metres.
        K: ``(3, 3)`` intrinsics, pixels.
        image_size: ``(H, W)``.
        generator: numpy random generator.

    Raises:
        ConfigError: no pose kept the points in view after ``max_tries`` draws.
    """
    H, W = check_image_size(image_size)
    points = np.asarray(points_root, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ShapeError(f"points_root: expected (N, 3) with N >= 1, got {points.shape}")
    K = np.asarray(K, dtype=np.float64)
    f = float(K[0, 0])
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    radius = max(float(np.linalg.norm(points - centre, axis=1).max()), 1e-6)
    for _ in range(max_tries):
        azimuth = generator.uniform(0.0, 2.0 * math.pi)
        elevation = math.radians(generator.uniform(*elevation_deg))
        towards_camera = np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        distance = f * 2.0 * radius / (generator.uniform(*fill_range) * min(H, W))
        forward = -towards_camera  # camera z, root frame
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        roll = math.radians(generator.uniform(-max_roll_deg, max_roll_deg))
        right, down = math.cos(roll) * right + math.sin(roll) * down, -math.sin(roll) * right + math.cos(roll) * down
        R = np.stack([right, down, forward])  # (3, 3) rows: camera axes in the root frame
        t = -R @ (centre + distance * towards_camera)
        cam = points @ R.T + t  # (N, 3)
        if cam[:, 2].min() <= 0.05 * distance:
            continue
        uv = cam[:, :2] / cam[:, 2:3] * f + K[:2, 2]  # (N, 2)
        low, high = uv.min(axis=0), uv.max(axis=0)
        slack_low = margin_px - low  # shift at least this much (negative: room to move towards 0)
        slack_high = np.array([W - 1.0, H - 1.0]) - margin_px - high
        if (slack_low > slack_high).any():
            continue
        shift = generator.uniform(slack_low, slack_high)  # (2,) pixels
        t = t + np.array([shift[0], shift[1], 0.0]) * distance / f
        cam = points @ R.T + t
        uv = cam[:, :2] / cam[:, 2:3] * f + K[:2, 2]
        inside = (uv >= margin_px).all() and (uv <= np.array([W - 1.0, H - 1.0]) - margin_px).all()
        if inside and cam[:, 2].min() > 0.05 * distance:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, t
            return T
    raise ConfigError(f"no camera pose kept the robot in the {W}x{H} image after {max_tries} draws; lower fill_range")


def random_colors(generator: np.random.Generator, count: int) -> np.ndarray:
    """``(count, 3)`` float64 BGR colours in [0, 255]: 75% saturated random hues, 25% white, grey or black."""
    colors = []
    for _ in range(count):
        if generator.uniform() < 0.25:
            hsv = (generator.uniform(0, 180), generator.uniform(0, 30), generator.uniform(40, 250))
        else:
            hsv = (generator.uniform(0, 180), generator.uniform(90, 255), generator.uniform(90, 255))
        colors.append(cv2.cvtColor(np.uint8([[hsv]]), cv2.COLOR_HSV2BGR)[0, 0])
    return np.asarray(colors, dtype=np.float64)


def random_lighting(generator: np.random.Generator) -> Lighting:
    """A random :class:`Lighting`: light from the camera's side, ambient 0.2-0.5, some specular half the time."""
    while True:
        d = generator.normal(size=3)
        d[2] = -abs(d[2]) - 0.3  # towards the camera (the camera looks along +z)
        norm = float(np.linalg.norm(d))
        if norm > 1e-6:
            break
    ambient = generator.uniform(0.2, 0.5)
    specular = generator.uniform(0.0, 0.5) if generator.uniform() < 0.5 else 0.0
    direction = tuple(float(v) for v in d / norm)
    return Lighting(
        direction_cam=direction,  # type: ignore[arg-type]
        ambient=ambient,
        diffuse=generator.uniform(0.5, 1.0) * (1.0 - ambient) + 0.2,
        specular=specular,
        shininess=generator.uniform(5.0, 60.0),
    )


def render_mesh_image(
    verts_cam: np.ndarray,
    faces: np.ndarray,
    face_colors_bgr: np.ndarray,
    K: np.ndarray,
    background: np.ndarray,
    lighting: Lighting = Lighting(),
) -> tuple[np.ndarray, np.ndarray]:
    """Draw a flat-shaded mesh over ``background``; return the image and the exact mask.

    Faces facing the camera are filled far to near (painter's algorithm, anti-aliased edges); the mask is
    ``pipeline.render.render_hard``'s silhouette of the whole mesh.

    Args:
        verts_cam: ``(V, 3)`` vertices in the camera frame, metres, all in front of the camera.
        faces: ``(F, 3)`` int triangles, counter-clockwise seen from outside (outward normals).
        face_colors_bgr: ``(F, 3)`` base colour of each face, BGR in [0, 255].
        K: ``(3, 3)`` intrinsics, pixels.
        background: ``(H, W, 3)`` uint8 BGR, not modified.
        lighting: the light.

    Returns:
        ``(image (H, W, 3) uint8 BGR, mask (H, W) bool)``.
    """
    verts = np.asarray(verts_cam, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise ShapeError(f"verts_cam: expected (V, 3), got {verts.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ShapeError(f"faces: expected (F, 3), got {faces.shape}")
    colors = np.asarray(face_colors_bgr, dtype=np.float64)
    if colors.shape != faces.shape:
        raise ShapeError(f"face_colors_bgr: expected {faces.shape} (one BGR colour per face), got {colors.shape}")
    if not isinstance(background, np.ndarray) or background.ndim != 3 or background.dtype != np.uint8:
        raise ShapeError("background: expected an (H, W, 3) uint8 BGR array")
    if verts[:, 2].min() < 1e-3:
        raise ShapeError("verts_cam: part of the mesh is at or behind the camera (z < 1 mm)")
    H, W = background.shape[:2]
    K = np.asarray(K, dtype=np.float64)
    mask = render_hard(
        torch.from_numpy(verts)[None], torch.from_numpy(faces), torch.from_numpy(K), (H, W)
    )[0].numpy()

    uv = verts[:, :2] / verts[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]  # (V, 2)
    tri = verts[faces]  # (F, 3, 3)
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-18)
    centroids = tri.mean(axis=1)  # (F, 3)
    front = (normals * centroids).sum(axis=1) < 0
    light = np.asarray(lighting.direction_cam, dtype=np.float64)
    light /= np.linalg.norm(light)
    view = -centroids / np.linalg.norm(centroids, axis=1, keepdims=True)  # (F, 3) towards the camera
    half = light + view
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-18)
    diffuse = np.clip(normals @ light, 0.0, 1.0)
    highlight = np.clip((normals * half).sum(axis=1), 0.0, 1.0) ** lighting.shininess
    shaded = colors * (lighting.ambient + lighting.diffuse * diffuse)[:, None]
    shaded += 255.0 * lighting.specular * highlight[:, None]
    shaded = np.clip(shaded, 0, 255)
    tri_px = np.round(uv * 16).astype(np.int32)[faces]  # (F, 3, 2), 4 fractional bits for cv2 (shift=4)
    image = background.copy()
    order = np.nonzero(front)[0][np.argsort(-centroids[front, 2])]
    for f in order:
        c = shaded[f]
        cv2.fillConvexPoly(image, tri_px[f], (float(c[0]), float(c[1]), float(c[2])), lineType=cv2.LINE_AA, shift=4)
    return image, mask


def random_background(
    generator: np.random.Generator,
    image_size: tuple[int, int],
    avoid_bgr: Sequence[Sequence[float]] | np.ndarray = (),
    *,
    min_chroma_distance: float = MIN_CHROMA_DISTANCE,
) -> np.ndarray:
    """``(H, W, 3)`` uint8 BGR clutter: a gradient, smooth texture, 15-40 flat shapes and 0-3 shaded blobs.

    Every colour keeps at least ``min_chroma_distance`` from each of ``avoid_bgr`` in the (a*, b*) plane of 8-bit
    Lab (so no clutter shares a robot colour's hue and chroma, whatever its brightness).
    """
    H, W = check_image_size(image_size)
    avoid = np.asarray(avoid_bgr, dtype=np.float64).reshape(-1, 3)
    avoid_ab = _lab(avoid)[:, 1:] if len(avoid) else np.zeros((0, 2))

    def colour() -> np.ndarray:
        for _ in range(1000):
            hsv = (generator.uniform(0, 180), generator.uniform(0, 255), generator.uniform(30, 245))
            bgr = cv2.cvtColor(np.uint8([[hsv]]), cv2.COLOR_HSV2BGR)[0, 0].astype(np.float64)
            if not len(avoid) or np.linalg.norm(avoid_ab - _lab(bgr[None])[0, 1:], axis=1).min() >= min_chroma_distance:
                return bgr
        raise ConfigError("random_background: found no clutter colour far enough from the robot colours")

    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    angle = generator.uniform(0.0, 2.0 * math.pi)
    ramp = math.cos(angle) * u / W + math.sin(angle) * v / H
    ramp = (ramp - ramp.min()) / max(float(np.ptp(ramp)), 1e-6)  # (H, W) in [0, 1]
    c0, c1 = colour().astype(np.float32), colour().astype(np.float32)
    image = c0 + (c1 - c0) * ramp[..., None]  # (H, W, 3) float32
    if generator.uniform() < 0.6:  # smooth brightness texture
        small = generator.uniform(0.75, 1.25, (int(generator.integers(2, 12)),) * 2).astype(np.float32)
        image *= cv2.resize(small, (W, H), interpolation=cv2.INTER_CUBIC)[..., None]
    image = np.clip(image, 0, 255).astype(np.uint8)
    scale = min(H, W)
    for _ in range(int(generator.integers(15, 41))):
        _draw_shape(image, generator, colour(), scale)
    for _ in range(int(generator.integers(0, 4))):
        _draw_blob(image, generator, colour(), scale)
    return image


def randomize_photometric(image: np.ndarray, generator: np.random.Generator) -> np.ndarray:
    """Random camera effects on an ``(H, W, 3)`` uint8 BGR image: colour cast, brightness, contrast, gamma, blur,
    Gaussian noise and (30% of the time) JPEG compression. Returns a new uint8 image."""
    x = image.astype(np.float32) / 255.0
    x *= generator.uniform(0.8, 1.2, 3).astype(np.float32)  # white balance
    mean = float(x.mean())
    x = (x - mean) * generator.uniform(0.7, 1.3) + mean + generator.uniform(-0.12, 0.12)
    x = np.clip(x, 0.0, 1.0) ** generator.uniform(0.7, 1.4)
    if generator.uniform() < 0.5:
        x = cv2.GaussianBlur(x, (0, 0), generator.uniform(0.3, 1.5))
    x += generator.normal(0.0, generator.uniform(0.0, 0.03), x.shape).astype(np.float32)
    out = np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)
    if generator.uniform() < 0.3:
        ok, data = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(generator.integers(35, 91))])
        out = cv2.imdecode(data, cv2.IMREAD_COLOR)
    return out


def _lab(bgr: np.ndarray) -> np.ndarray:
    """``(N, 3)`` BGR in [0, 255] -> ``(N, 3)`` 8-bit Lab (L, a, b each in [0, 255], a and b centred on 128)."""
    pixels = np.clip(np.round(bgr), 0, 255).astype(np.uint8)[None]  # (1, N, 3)
    return cv2.cvtColor(pixels, cv2.COLOR_BGR2LAB)[0].astype(np.float64)


def _draw_shape(image: np.ndarray, generator: np.random.Generator, bgr: np.ndarray, scale: int) -> None:
    H, W = image.shape[:2]
    c = tuple(float(v) for v in bgr)
    x, y = int(generator.integers(0, W)), int(generator.integers(0, H))
    size = max(int(generator.uniform(0.03, 0.25) * scale), 2)
    kind = int(generator.integers(0, 5))
    if kind == 0:
        x2, y2 = x + int(generator.uniform(-2, 2) * size), y + int(generator.uniform(-2, 2) * size)
        cv2.rectangle(image, (x, y), (x2, y2), c, -1)
    elif kind == 1:
        cv2.circle(image, (x, y), size, c, -1, cv2.LINE_AA)
    elif kind == 2:
        axes = (size, max(int(size * generator.uniform(0.2, 1.0)), 1))
        cv2.ellipse(image, (x, y), axes, generator.uniform(0, 180), 0, 360, c, -1, cv2.LINE_AA)
    elif kind == 3:
        x2, y2 = int(generator.integers(0, W)), int(generator.integers(0, H))
        cv2.line(image, (x, y), (x2, y2), c, int(generator.integers(1, 6)), cv2.LINE_AA)
    else:
        n = int(generator.integers(3, 7))
        angles = np.sort(generator.uniform(0, 2 * math.pi, n))
        radii = size * generator.uniform(0.4, 1.2, n)
        pts = np.stack([x + radii * np.cos(angles), y + radii * np.sin(angles)], axis=1).astype(np.int32)
        cv2.fillPoly(image, [pts], c, cv2.LINE_AA)


def _draw_blob(image: np.ndarray, generator: np.random.Generator, bgr: np.ndarray, scale: int) -> None:
    """A shaded ellipse (radial gradient), a distractor that looks three-dimensional."""
    H, W = image.shape[:2]
    cx, cy = generator.uniform(0, W), generator.uniform(0, H)
    a, b = generator.uniform(0.03, 0.15) * scale, generator.uniform(0.03, 0.15) * scale
    theta = generator.uniform(0, math.pi)
    x0, x1 = int(max(cx - max(a, b) - 1, 0)), int(min(cx + max(a, b) + 2, W))
    y0, y1 = int(max(cy - max(a, b) - 1, 0)), int(min(cy + max(a, b) + 2, H))
    if x1 <= x0 or y1 <= y0:
        return
    v, u = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    du, dv = u - cx, v - cy
    p = (math.cos(theta) * du + math.sin(theta) * dv) / a
    q = (-math.sin(theta) * du + math.cos(theta) * dv) / b
    r2 = p * p + q * q
    inside = r2 <= 1.0
    shade = 0.45 + 0.55 * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))  # brighter at the centre
    patch = image[y0:y1, x0:x1]
    patch[inside] = np.clip(bgr[None] * shade[inside][:, None], 0, 255).astype(np.uint8)
