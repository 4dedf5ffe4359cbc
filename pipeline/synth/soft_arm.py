"""Synthetic soft-arm data for tests and demos: random centrelines in view and rendered images with their masks.

Convention: camera frame (OpenCV: x right, y down, z forward), metres; pixels ``(u, v)`` = (column, row) with
pixel centres at integer coordinates; images are BGR uint8 as OpenCV writes them; masks are ``(H, W)`` bool.
All randomness comes from the ``numpy.random.Generator`` passed in, so a seed reproduces the data exactly.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
from scipy.spatial.transform import Rotation

from pipeline.camera import project_points
from pipeline.checks import check_image_size, check_positive
from pipeline.errors import ConfigError, ShapeError
from pipeline.render import render_hard
from pipeline.shapes.bezier import bezier_points
from pipeline.shapes.frames import initial_normal, rotation_minimizing_frames
from pipeline.shapes.polyline import polyline_arc_length, resample_polyline
from pipeline.shapes.tube import tube_faces, tube_vertices

__all__ = ["random_bezier_arm", "moving_bezier_arm", "moving_pcc_arm", "pcc_arm", "pcc_centerline", "place_in_view",
           "render_tube_image", "tube_mesh", "resample_polyline", "DEFAULT_ARM_COLOR_BGR"]

#: A saturated pink-red, far in hue from the background clutter (which avoids +-25 degrees of the arm's hue).
DEFAULT_ARM_COLOR_BGR = (90, 70, 230)


def random_bezier_arm(
    generator: np.random.Generator,
    K: np.ndarray,
    image_size: tuple[int, int],
    *,
    length_m: float = 0.2,
    distance_m: float = 0.4,
    order: int = 2,
    max_bend_rad: float = 2.0,
    margin_px: float = 20.0,
    base_nearer_border: bool = True,
    max_tries: int = 200,
) -> np.ndarray:
    """Control points of a random Bezier arm seen whole by the camera.

    The control polygon has ``order`` legs of random length (0.7 to 1.3 of the mean) turning by random angles
    about random axes, a total turn of at most ``max_bend_rad`` (a cubic may bend both ways: an S). It is scaled
    so that the curve's arc length is ``length_m`` (to 1e-6 relative), rotated uniformly at random and moved so
    that its centroid (of points uniform in arc length) lies ``distance_m`` from the camera on the ray through a
    random pixel of the central half of the image; drawn again until every curve point projects at least
    ``margin_px`` inside the image (and, with ``base_nearer_border``, until the base projects at least 10 px
    nearer the image border than the tip, so that ``pipeline.preprocess.skeleton_path``'s default base rule
    holds).

    Args:
        generator: numpy random generator (seeded by the caller).
        K: ``(3, 3)`` camera intrinsics, pixels.
        image_size: ``(H, W)``.
        length_m: arc length of the centreline, metres.
        distance_m: distance from the camera centre to the centroid of the curve, metres.
        order: Bezier order ``n >= 1`` (``n + 1`` control points).
        max_bend_rad: largest total turn of the control polygon, radians.
        margin_px: smallest distance from a projected curve point to the image border, pixels.
        base_nearer_border: require the base to be nearer the image border than the tip.
        max_tries: draws before giving up.

    Returns:
        ``(order + 1, 3)`` float64 control points in the camera frame, metres, base first.

    Raises:
        ConfigError: no draw fits in the image (make the arm shorter or the distance larger).
    """
    if isinstance(order, bool) or not isinstance(order, int) or order < 1:
        raise ConfigError(f"order: expected an int >= 1, got {order!r}")
    check_positive(length_m, "length_m")
    s = torch.linspace(0.0, 1.0, 2001, dtype=torch.float64)

    def curve(cp: np.ndarray) -> np.ndarray:
        return bezier_points(torch.from_numpy(cp)[None], s)[0].numpy()  # (2001, 3)

    direction = np.array([1.0, 0.0, 0.0])
    legs = []
    for leg in range(order):
        if leg > 0:
            angle = generator.uniform(0.3, 1.0) * max_bend_rad / max(order - 1, 1)
            direction = _rotate(direction, _random_perpendicular(generator, direction), angle)
        legs.append(direction * generator.uniform(0.7, 1.3))
    local = np.concatenate([np.zeros((1, 3)), np.cumsum(legs, axis=0)])  # (n+1, 3)
    local *= length_m / polyline_arc_length(curve(local))[-1]
    samples = resample_polyline(curve(local), 201)  # (201, 3) uniform in arc length
    R, t = _place_in_view(generator, samples, K, image_size, distance_m, margin_px, base_nearer_border, max_tries)
    return local @ R.T + t


def moving_bezier_arm(
    generator: np.random.Generator,
    K: np.ndarray,
    image_size: tuple[int, int],
    n_frames: int,
    *,
    length_m: float = 0.2,
    distance_m: float = 0.4,
    order: int = 2,
    amplitude_rad: float = 1.0,
    period_frames: float = 50.0,
    margin_px: float = 20.0,
    max_tries: int = 200,
) -> np.ndarray:
    """Control points of a Bezier arm moving over ``n_frames`` video frames, its base and base direction fixed.

    The control polygon has ``order`` legs (random lengths 0.7 to 1.3 of the mean, fixed); the first leaves the
    base along a fixed direction and each later leg turns from the previous one by ``a_j(t) = amplitude_rad
    sin(2 pi t / period_frames + phi_j)`` about an axis tilted out of the bending plane by a random angle up to
    0.5 rad (so the arm moves in 3D): every joint bends one way, then the other, and with ``order >= 3`` the
    phases ``phi_j`` (random) make S shapes in some frames. Each frame is scaled about the base so that its arc
    length is ``length_m``. One rigid placement, drawn like ``random_bezier_arm``'s, puts every frame in view
    (each curve point ``margin_px`` inside the image) with the base at least 10 px nearer the image border than
    the tip in every frame.

    Args:
        generator: numpy random generator (seeded by the caller).
        K: ``(3, 3)`` camera intrinsics, pixels.
        image_size: ``(H, W)``.
        n_frames: frames ``T >= 1``.
        length_m, distance_m, order, margin_px, max_tries: as in ``random_bezier_arm``.
        amplitude_rad: largest turn of each joint of the control polygon, radians.
        period_frames: frames of one full bending cycle.

    Returns:
        ``(T, order + 1, 3)`` float64 control points in the camera frame, metres, base first.

    Raises:
        ConfigError: bad arguments, or no placement keeps every frame in view.
    """
    _check_moving(order, "order", n_frames, length_m, period_frames)
    check_positive(amplitude_rad, "amplitude_rad", allow_zero=True)
    s = torch.linspace(0.0, 1.0, 1001, dtype=torch.float64)
    leg_lengths = generator.uniform(0.7, 1.3, order)
    phases = generator.uniform(0.0, 2.0 * math.pi, order)
    tilts = generator.uniform(-0.5, 0.5, order)
    frames = []
    for t in range(n_frames):
        direction = np.array([1.0, 0.0, 0.0])
        legs = []
        for leg in range(order):
            if leg > 0:
                axis = np.array([0.0, math.sin(tilts[leg]), math.cos(tilts[leg])])  # ~z, tilted towards y
                axis -= (axis @ direction) * direction
                angle = amplitude_rad * math.sin(2.0 * math.pi * t / period_frames + phases[leg])
                direction = _rotate(direction, axis / np.linalg.norm(axis), angle)
            legs.append(direction * leg_lengths[leg])
        local = np.concatenate([np.zeros((1, 3)), np.cumsum(legs, axis=0)])  # (n+1, 3), base at the origin
        curve = bezier_points(torch.from_numpy(local)[None], s)[0].numpy()
        frames.append(local * (length_m / polyline_arc_length(curve)[-1]))
    local = np.stack(frames)  # (T, n+1, 3)
    samples = np.stack([resample_polyline(bezier_points(torch.from_numpy(c)[None], s)[0].numpy(), 51)
                        for c in local])  # (T, 51, 3)
    R, t = _place_moving(generator, samples, K, image_size, distance_m, margin_px, max_tries)
    return local @ R.T + t


def _check_moving(parts: int, name: str, n_frames: int, length_m: float, period_frames: float) -> None:
    """The checks of a moving arm's arguments: ``parts`` (``name``: its legs or sections) and ``n_frames`` ints
    >= 1, ``length_m`` and ``period_frames`` > 0; a ``ConfigError`` naming the first bad one."""
    for value, label in ((parts, name), (n_frames, "n_frames")):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ConfigError(f"{label}: expected an int >= 1, got {value!r}")
    check_positive(length_m, "length_m")
    check_positive(period_frames, "period_frames")


def _place_moving(generator: np.random.Generator, samples: np.ndarray, K: np.ndarray, image_size: tuple[int, int],
                  distance_m: float, margin_px: float, max_tries: int) -> tuple[np.ndarray, np.ndarray]:
    """One rigid placement ``(R, t)`` of a moving arm's centrelines ``(T, P, 3)`` (its own frame, base first) that
    keeps every frame in view (``margin_px`` inside the image) with the base at least 10 px nearer the image border
    than the tip in every frame, drawn like ``random_bezier_arm``'s.

    Raises:
        ConfigError: no such placement in ``max_tries`` draws.
    """
    H, W = check_image_size(image_size)
    K = _check_K(K)
    for _ in range(max_tries):
        try:
            R, t = _place_in_view(generator, samples.reshape(-1, 3), K, image_size, distance_m, margin_px, False, 1)
        except ConfigError:  # this draw left the image or came too near the camera
            continue
        cam = samples @ R.T + t  # (T, P, 3)
        uv = cam[..., :2] / cam[..., 2:3] * np.diag(K)[:2] + K[:2, 2]  # (T, P, 2)
        ends = np.stack([uv[:, 0], uv[:, -1]], axis=1)  # (T, 2, 2) base and tip pixels
        border = np.minimum(np.minimum(ends[..., 0], ends[..., 1]),
                            np.minimum(W - 1 - ends[..., 0], H - 1 - ends[..., 1]))  # (T, 2)
        if (border[:, 0] <= border[:, 1] - 10.0).all():
            return R, t
    raise ConfigError(
        f"no placement of the moving arm kept all {len(samples)} frames in the {W}x{H} image with the base nearer "
        f"the border after {max_tries} draws: make the arm shorter, the distance larger or the bends smaller"
    )


def moving_pcc_arm(
    generator: np.random.Generator,
    K: np.ndarray,
    image_size: tuple[int, int],
    n_frames: int,
    *,
    length_m: float = 0.2,
    distance_m: float = 0.4,
    sections: int = 2,
    max_curvature_per_m: float = 15.0,
    period_frames: float = 50.0,
    n_points: int = 101,
    margin_px: float = 20.0,
    max_tries: int = 200,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A piecewise-constant-curvature arm (equal sections, not a Bezier curve) moving over ``n_frames`` video frames,
    its base and base direction fixed: a tendon-driven multi-section arm.

    Section ``i`` bends with a signed curvature ``k_i(t) = k_i sin(2 pi t / period_frames + phi_i)`` in a plane at
    ``theta_i(t) = theta_i + 0.4 sin(pi t / period_frames + psi_i)`` about its tangent (in the frame the previous
    section ends in), ``k_i`` uniform in ``[0.5, 1] * max_curvature_per_m``, ``phi_i``, ``theta_i``, ``psi_i``
    random: each section bends one way, then the other, its plane swinging, and the sections' phases make S shapes
    and out-of-plane bends in some frames. One placement for every frame, as ``moving_bezier_arm``'s.

    Args:
        generator: numpy random generator (seeded by the caller).
        K, image_size, n_frames, length_m, distance_m, period_frames, margin_px, max_tries: as
            ``moving_bezier_arm``.
        sections: constant-curvature sections (>= 1).
        max_curvature_per_m: the largest curvature of a section, 1/m (>= 0).
        n_points: centreline points per frame.

    Returns:
        ``(centrelines (T, n_points, 3), curvatures (T, sections) >= 0, plane angles (T, sections))``: camera frame,
        metres, base first, uniform in arc length; 1/m; radians (a negative curvature turned into its plane plus
        pi), as ``pcc_centerline`` takes them.

    Raises:
        ConfigError: bad arguments, or no placement keeps every frame in view.
    """
    _check_moving(sections, "sections", n_frames, length_m, period_frames)
    check_positive(max_curvature_per_m, "max_curvature_per_m", allow_zero=True)
    peaks = generator.uniform(0.5, 1.0, sections) * max_curvature_per_m
    phases, planes, swings = (generator.uniform(0.0, 2.0 * math.pi, sections) for _ in range(3))
    t = np.arange(n_frames)[:, None]
    signed = peaks * np.sin(2.0 * math.pi * t / period_frames + phases)  # (T, N)
    angles = planes + 0.4 * np.sin(math.pi * t / period_frames + swings) + np.where(signed < 0, math.pi, 0.0)
    curvatures, angles = np.abs(signed), np.mod(angles, 2.0 * math.pi)
    lengths = [length_m / sections] * sections
    local = np.stack([pcc_centerline(list(k), list(a), lengths, n_points) for k, a in zip(curvatures, angles)])
    R, shift = _place_moving(generator, local, K, image_size, distance_m, margin_px, max_tries)
    return local @ R.T + shift, curvatures, angles


def pcc_arm(
    generator: np.random.Generator,
    K: np.ndarray,
    image_size: tuple[int, int],
    *,
    length_m: float = 0.2,
    distance_m: float = 0.4,
    n_segments: int = 2,
    max_bend_rad: float = 2.0,
    n_points: int = 101,
    margin_px: float = 20.0,
    base_nearer_border: bool = True,
    max_tries: int = 200,
) -> np.ndarray:
    """Centreline of a random piecewise-constant-curvature arm (not a Bezier curve) seen whole by the camera.

    ``n_segments`` arcs of equal length; each bends by a random angle in ``[0.2, 1] * max_bend_rad / n_segments``
    in a bending plane at a random angle about the tangent (so consecutive arcs may bend opposite ways). Placed
    like ``random_bezier_arm``.

    Args:
        generator: numpy random generator.
        K: ``(3, 3)`` camera intrinsics, pixels.
        image_size: ``(H, W)``.
        length_m: arc length, metres.
        distance_m: distance from the camera to the centroid of the centreline, metres.
        n_segments: number of constant-curvature arcs.
        max_bend_rad: largest total bend, radians.
        n_points: output points.
        margin_px, base_nearer_border, max_tries: as in ``random_bezier_arm``.

    Returns:
        ``(n_points, 3)`` float64 centreline in the camera frame, metres, uniform in arc length, base first.
    """
    if isinstance(n_segments, bool) or not isinstance(n_segments, int) or n_segments < 1:
        raise ConfigError(f"n_segments: expected an int >= 1, got {n_segments!r}")
    check_positive(length_m, "length_m")
    curvatures, planes = [], []
    for _ in range(n_segments):
        curvatures.append(generator.uniform(0.2, 1.0) * max_bend_rad / n_segments / (length_m / n_segments))
        planes.append(generator.uniform(0.0, 2.0 * math.pi))
    local = pcc_centerline(curvatures, planes, [length_m / n_segments] * n_segments, n_points)
    return place_in_view(generator, local, K, image_size, distance_m=distance_m, margin_px=margin_px,
                         base_nearer_border=base_nearer_border, max_tries=max_tries)


def pcc_centerline(
    curvatures_per_m: list[float],
    plane_angles_rad: list[float],
    section_lengths_m: list[float],
    n_points: int = 101,
) -> np.ndarray:
    """Centreline of piecewise-constant-curvature sections, in the arm's own frame (base at the origin, leaving
    along +z).

    Section ``i`` is an arc of curvature ``curvatures_per_m[i]`` (>= 0) and length ``section_lengths_m[i]``,
    bending in the plane at angle ``plane_angles_rad[i]`` about the tangent, measured in the frame the previous
    section ends in (the frame is carried along each arc by rotating about the bending axis; at the base it is
    the identity: body x, y, z = tangent). Integrated in 400 exact chord steps per section.

    Returns:
        ``(n_points, 3)`` float64, uniform in arc length, base first, metres.
    """
    if not len(curvatures_per_m) == len(plane_angles_rad) == len(section_lengths_m) >= 1:
        raise ConfigError(
            f"pcc_centerline: expected as many curvatures, plane angles and section lengths (>= 1), got "
            f"{len(curvatures_per_m)}, {len(plane_angles_rad)}, {len(section_lengths_m)}"
        )
    steps_per_segment = 400
    frame = np.eye(3)  # columns: body x, y, z; z is the tangent
    position = np.zeros(3)
    points = [position]
    for curvature, plane, length in zip(curvatures_per_m, plane_angles_rad, section_lengths_m):
        check_positive(length, "section length")
        ds = length / steps_per_segment
        axis_body = np.array([math.cos(plane), math.sin(plane), 0.0])
        half = Rotation.from_rotvec(0.5 * curvature * ds * axis_body).as_matrix()
        chord = ds * np.sinc(0.5 * curvature * ds / math.pi)  # 2 sin(k ds / 2) / k, exact for an arc
        for _ in range(steps_per_segment):
            frame = frame @ half
            position = position + chord * frame[:, 2]
            frame = frame @ half
            points.append(position)
    return resample_polyline(np.asarray(points), n_points)


def place_in_view(
    generator: np.random.Generator,
    local_points: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    *,
    distance_m: float = 0.4,
    margin_px: float = 20.0,
    base_nearer_border: bool = True,
    max_tries: int = 200,
) -> np.ndarray:
    """``local_points`` ``(N, 3)`` (an arm in its own frame, base first) under a random rotation, its centroid on
    the ray of a random pixel in the middle half of the image at ``distance_m``, seen whole (``margin_px`` from
    the border) with its base nearer the border when ``base_nearer_border``: ``(N, 3)`` camera frame, metres.

    Raises:
        ConfigError: no such placement in ``max_tries`` draws.
    """
    R, t = _place_in_view(generator, local_points, K, image_size, distance_m, margin_px, base_nearer_border, max_tries)
    return local_points @ R.T + t


def render_tube_image(
    centerline_cam_m: np.ndarray,
    radii_m: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    generator: np.random.Generator,
    *,
    n_angles: int = 40,
    arm_color_bgr: tuple[int, int, int] = DEFAULT_ARM_COLOR_BGR,
    noise_std: float = 3.0,
    supersample: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Draw a tube (hard edges, OpenCV) over a cluttered random background; return the image and the true mask.

    The tube mesh of ``pipeline.shapes.tube`` (rotation-minimising frames, one ring per centreline point, capped)
    is projected with the pinhole ``K``; the mask holds the pixels whose centre lies in a projected triangle
    (``pipeline.render.render_hard``: the exact silhouette of the mesh, as the soft rasterizer samples it); the arm
    is the front-facing triangles, far to near, Lambert-shaded in ``arm_color_bgr``.
    The background is a colour gradient with 20-40 random rectangles, circles, ellipses and lines whose hue stays
    25 degrees or more from the arm's (or whose saturation is low); then a 3x3 Gaussian blur and Gaussian noise.

    Args:
        centerline_cam_m: ``(N, 3)`` dense centreline base to tip (camera frame, metres), ``N >= 2`` (use 50+).
        radii_m: ``(N,)`` tube radius at each centreline point, metres.
        K: ``(3, 3)`` intrinsics, pixels.
        image_size: ``(H, W)``.
        generator: numpy random generator for the background and the noise.
        n_angles: vertices per ring.
        arm_color_bgr: the arm's colour before shading.
        noise_std: standard deviation of the pixel noise (grey levels).
        supersample: 1 draws the arm's triangles with OpenCV's anti-aliasing, which widens a filled polygon by
            about 0.66 px on every side (the drawn arm is wider than ``mask``: about 5 % more area for a 15 px
            radius); ``n > 1`` draws them without anti-aliasing at ``n`` times the resolution (around the arm) and
            averages each pixel's ``n x n`` samples, so a rim pixel's colour mixes arm and background by its
            covered area, as a camera's does (the arm then has ``mask``'s area). The background and noise draws
            are the same either way.

    Returns:
        ``(image (H, W, 3) uint8 BGR, mask (H, W) bool)``.

    Raises:
        ShapeError: bad shapes, or part of the tube at or behind the camera (z < 1 mm).
    """
    H, W = check_image_size(image_size)
    centerline = np.asarray(centerline_cam_m, dtype=np.float64)
    radii = np.asarray(radii_m, dtype=np.float64)
    if centerline.ndim != 2 or centerline.shape[1] != 3 or centerline.shape[0] < 2:
        raise ShapeError(f"centerline_cam_m: expected (N, 3) with N >= 2, got {centerline.shape}")
    if radii.shape != (centerline.shape[0],) or not (radii > 0).all():
        raise ShapeError(f"radii_m: expected ({centerline.shape[0]},) values > 0, got shape {radii.shape}")
    K = _check_K(K)

    verts, faces = tube_mesh(centerline, radii, n_angles)
    verts, faces = verts[None], faces.numpy()  # (1, V, 3), (F, 3)
    if float(verts[..., 2].min()) < 1e-3:
        raise ShapeError("centerline_cam_m: part of the tube is at or behind the camera (z < 1 mm)")
    uv = project_points(verts, torch.from_numpy(K))[0].numpy()  # (V, 2)
    if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
        raise ConfigError(f"supersample: expected an int >= 1, got {supersample!r}")
    if np.abs(uv).max() >= 2**26:
        raise ShapeError("centerline_cam_m: the tube projects absurdly far outside the image")
    mask = render_hard(verts, torch.from_numpy(faces), torch.from_numpy(K), (H, W))[0].numpy()
    verts = verts[0].numpy()
    image = _background(generator, (H, W), arm_color_bgr)
    tri_px = np.round(uv * 16).astype(np.int32)[faces]  # (F, 3, 2) with 4 fractional bits for cv2 (shift=4)

    tri_xyz = verts[faces]  # (F, 3, 3)
    normals = np.cross(tri_xyz[:, 1] - tri_xyz[:, 0], tri_xyz[:, 2] - tri_xyz[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-18)
    centroids = tri_xyz.mean(axis=1)
    front = (normals * centroids).sum(axis=1) < 0  # facing the camera
    light = np.array([0.3, -0.5, -1.0]) / math.sqrt(0.09 + 0.25 + 1.0)  # towards the upper-left, near the camera
    shade = 0.35 + 0.65 * np.clip(normals @ light, 0.0, 1.0)
    colour = np.asarray(arm_color_bgr, dtype=np.float64)
    order = np.nonzero(front)[0][np.argsort(-centroids[front, 2])]  # far to near
    if supersample == 1:
        for f in order:
            c = tuple(int(v) for v in np.clip(colour * shade[f], 0, 255))
            cv2.fillConvexPoly(image, tri_px[f], c, lineType=cv2.LINE_AA, shift=4)
    else:
        _draw_area_averaged(image, uv[faces][order], np.clip(colour * shade[order, None], 0, 255), supersample)

    image = cv2.GaussianBlur(image, (3, 3), 0).astype(np.float64)
    image += generator.normal(0.0, noise_std, image.shape)
    return np.clip(np.round(image), 0, 255).astype(np.uint8), mask


def _draw_area_averaged(image: np.ndarray, triangles_uv: np.ndarray, colours: np.ndarray, n: int) -> None:
    """Paint triangles ``(F, 2-D pixels (3, 2))`` in ``colours`` ``(F, 3)`` (in that order, later on top) into
    ``image`` ``(H, W, 3)`` uint8, in place, each pixel mixing by its covered area: drawn without anti-aliasing
    at ``n`` times the resolution in the triangles' bounding box, then averaged over ``n x n`` samples."""
    H, W = image.shape[:2]
    x0 = max(int(math.floor(triangles_uv[..., 0].min())) - 1, 0)
    y0 = max(int(math.floor(triangles_uv[..., 1].min())) - 1, 0)
    x1 = min(int(math.ceil(triangles_uv[..., 0].max())) + 2, W)
    y1 = min(int(math.ceil(triangles_uv[..., 1].max())) + 2, H)
    if x1 <= x0 or y1 <= y0:
        return
    # Fine pixel (i, j) covers coarse pixel ((j + 0.5) / n - 0.5 + x0, ...): its centre in fine pixels is
    # n (u - x0 + 0.5) - 0.5; 4 fractional bits for cv2 (shift=4).
    fine = np.round(((triangles_uv - [x0, y0] + 0.5) * n - 0.5) * 16).astype(np.int32)  # (F, 3, 2)
    colour_layer = np.zeros(((y1 - y0) * n, (x1 - x0) * n, 3), np.float32)
    cover = np.zeros(colour_layer.shape[:2], np.uint8)
    for triangle, c in zip(fine, colours):
        cv2.fillConvexPoly(colour_layer, triangle, tuple(float(v) for v in c), lineType=cv2.LINE_8, shift=4)
        cv2.fillConvexPoly(cover, triangle, 1, lineType=cv2.LINE_8, shift=4)
    shape = (y1 - y0, n, x1 - x0, n)
    alpha = cover.astype(np.float32).reshape(shape).mean(axis=(1, 3))[..., None]  # (h, w, 1) covered area
    painted = colour_layer.reshape(shape + (3,)).mean(axis=(1, 3))  # (h, w, 3) arm colour times coverage
    region = image[y0:y1, x0:x1].astype(np.float32)
    image[y0:y1, x0:x1] = np.clip(np.round(region * (1.0 - alpha) + painted), 0, 255).astype(np.uint8)


def tube_mesh(centerline: np.ndarray, radii: np.ndarray, n_angles: int = 40) -> tuple[torch.Tensor, torch.Tensor]:
    """The capped tube mesh of ``pipeline.shapes.tube`` around a centreline (rotation-minimising frames started
    from central-difference tangents, one ring of ``n_angles`` vertices per centreline point).

    Args:
        centerline: ``(N, 3)`` float64 points base to tip, metres.
        radii: ``(N,)`` float64 radius at each point, metres.
        n_angles: vertices per ring.

    Returns:
        ``(verts (V, 3) float64, faces (F, 3) int64)`` tensors, in the frame of ``centerline``.
    """
    points = torch.from_numpy(centerline)[None]  # (1, N, 3)
    tangents = torch.from_numpy(np.gradient(centerline, axis=0))[None]  # (1, N, 3), central differences
    normal = initial_normal(tangents[:, 0], torch.zeros_like(tangents[:, 0]))
    frames = rotation_minimizing_frames(points, tangents, normal)
    verts = tube_vertices(points, frames, torch.from_numpy(radii)[None], n_angles)[0]  # (V, 3)
    return verts, tube_faces(centerline.shape[0], n_angles)


def _background(
    generator: np.random.Generator, image_size: tuple[int, int], arm_bgr: tuple[int, int, int]
) -> np.ndarray:
    """``(H, W, 3)`` uint8 BGR gradient with random shapes whose hue keeps away from ``arm_bgr``'s."""
    H, W = image_size
    arm_hue = float(cv2.cvtColor(np.uint8([[arm_bgr]]), cv2.COLOR_BGR2HSV)[0, 0, 0]) * 2.0  # degrees

    def colour() -> tuple[int, int, int]:
        while True:
            hue = generator.uniform(0.0, 360.0)
            saturation = generator.uniform(0.0, 1.0)
            far = abs((hue - arm_hue + 180.0) % 360.0 - 180.0) >= 25.0
            if far or saturation < 0.25:
                break
        value = generator.uniform(0.2, 0.95)
        hsv = np.uint8([[[hue / 2.0, saturation * 255.0, value * 255.0]]])
        return tuple(int(c) for c in cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)[0, 0])

    angle = generator.uniform(0.0, 2.0 * math.pi)
    v, u = np.mgrid[0:H, 0:W]
    ramp = (math.cos(angle) * u / W + math.sin(angle) * v / H)
    ramp = (ramp - ramp.min()) / max(float(np.ptp(ramp)), 1e-9)  # (H, W) in [0, 1]
    c0, c1 = np.array(colour(), np.float64), np.array(colour(), np.float64)
    image = np.ascontiguousarray(c0 + (c1 - c0) * ramp[..., None]).astype(np.uint8)
    scale = min(H, W)
    for _ in range(int(generator.integers(20, 41))):
        kind = int(generator.integers(0, 4))
        c = colour()
        x, y = int(generator.integers(0, W)), int(generator.integers(0, H))
        size = int(generator.uniform(0.03, 0.25) * scale)
        if kind == 0:
            x2, y2 = x + int(generator.uniform(-1, 1) * size * 2), y + int(generator.uniform(-1, 1) * size * 2)
            cv2.rectangle(image, (x, y), (x2, y2), c, -1)
        elif kind == 1:
            cv2.circle(image, (x, y), max(size, 2), c, -1, cv2.LINE_AA)
        elif kind == 2:
            axes = (max(size, 2), max(int(size * generator.uniform(0.2, 1.0)), 1))
            cv2.ellipse(image, (x, y), axes, generator.uniform(0, 180), 0, 360, c, -1, cv2.LINE_AA)
        else:
            x2, y2 = int(generator.integers(0, W)), int(generator.integers(0, H))
            cv2.line(image, (x, y), (x2, y2), c, int(generator.integers(1, 6)), cv2.LINE_AA)
    return image


def _place_in_view(
    generator: np.random.Generator,
    local_points: np.ndarray,
    K: np.ndarray,
    image_size: tuple[int, int],
    distance_m: float,
    margin_px: float,
    base_nearer_border: bool,
    max_tries: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Random ``(R (3, 3), t (3,))`` putting ``local_points`` ``(N, 3)`` in view; see ``random_bezier_arm``."""
    H, W = check_image_size(image_size)
    K = _check_K(K)
    check_positive(distance_m, "distance_m")
    centroid = local_points.mean(axis=0)
    K_inv = np.linalg.inv(K)
    for _ in range(max_tries):
        R = _random_rotation(generator)
        pixel = np.array([generator.uniform(0.25, 0.75) * (W - 1), generator.uniform(0.25, 0.75) * (H - 1), 1.0])
        ray = K_inv @ pixel
        t = distance_m * ray / np.linalg.norm(ray) - R @ centroid
        cam = local_points @ R.T + t  # (N, 3)
        if cam[:, 2].min() <= 0.05 * distance_m:
            continue
        uv = (cam / cam[:, 2:3]) @ K.T  # (N, 3) homogeneous pixels
        u, v = uv[:, 0], uv[:, 1]
        border = np.minimum(np.minimum(u, v), np.minimum(W - 1 - u, H - 1 - v))  # (N,) distance to the border
        if border.min() < margin_px:
            continue
        if not base_nearer_border or border[0] <= border[-1] - 10.0:
            return R, t
    raise ConfigError(
        f"no random arm fitted in the {W}x{H} image after {max_tries} draws at {distance_m} m: "
        "make the arm shorter or the distance larger"
    )


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.isfinite(K).all():
        raise ShapeError(f"K: expected a finite (3, 3) intrinsic matrix, got shape {K.shape}")
    return K


def _random_rotation(generator: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (from a uniform unit quaternion (w, x, y, z): four normal draws)."""
    return Rotation.from_quat(generator.normal(size=4), scalar_first=True).as_matrix()


def _random_perpendicular(generator: np.random.Generator, direction: np.ndarray) -> np.ndarray:
    while True:
        v = generator.normal(size=3)
        v -= (v @ direction) * direction
        norm = np.linalg.norm(v)
        if norm > 1e-6:
            return v / norm


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """``v`` rotated by ``angle`` (radians) about the unit ``axis``."""
    return Rotation.from_rotvec(angle * axis).apply(v)
