"""Soft rasterizer: fast backends against the naive dense reference, gradcheck, degenerate input, errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from pipeline.camera import project_points
from pipeline.errors import ConfigError, ShapeError
from pipeline.render import (
    SoftRasterSettings,
    render_hard,
    render_silhouette,
    render_silhouette_packed,
    soft_rasterize,
)
from pipeline.render.reference import naive_soft_rasterize

BACKENDS = ("numba", "torch")
H, W = 20, 28
K = torch.tensor([[40.0, 0.0, 13.5], [0.0, 40.0, 9.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def random_mesh(seed: int, n_verts: int = 9, n_faces: int = 7, batch: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """A random triangle soup in front of the camera: verts (B, V, 3), faces (F, 3)."""
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(batch, n_verts, 2, generator=g, dtype=torch.float64) - 0.5) * 0.35
    z = 0.5 + 0.2 * torch.rand(batch, n_verts, 1, generator=g, dtype=torch.float64)
    faces = torch.stack([torch.randperm(n_verts, generator=g)[:3] for _ in range(n_faces)])
    return torch.cat([xy * z / 0.5, z], dim=-1), faces


def naive_render(verts: torch.Tensor, faces: torch.Tensor, settings: SoftRasterSettings) -> torch.Tensor:
    B, V, _ = verts.shape
    uv = project_points(verts, K.to(verts)).reshape(-1, 2)
    packed = (faces[None] + torch.arange(B)[:, None, None] * V).reshape(-1, 3)
    return naive_soft_rasterize(uv, verts.reshape(-1, 3)[:, 2], packed, torch.arange(B).repeat_interleave(len(faces)),
                                B, (H, W), settings)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("sigma_px2", [0.5, 3.0])
def test_values_and_gradients_match_naive_reference(backend, sigma_px2):
    settings = SoftRasterSettings.from_sigma(sigma_px2, backend=backend, saturation=60.0)
    verts, faces = random_mesh(1, batch=2)
    target = (torch.rand(2, H, W, generator=torch.Generator().manual_seed(2), dtype=torch.float64) > 0.5).double()
    fast_v = verts.clone().requires_grad_(True)
    ref_v = verts.clone().requires_grad_(True)
    fast = render_silhouette(fast_v, faces, K, (H, W), settings)
    ref = naive_render(ref_v, faces, settings)
    assert fast.shape == (2, H, W) and fast.dtype == torch.float64
    torch.testing.assert_close(fast, ref, atol=1e-10, rtol=0)
    ((fast - target) ** 2).sum().backward()
    ((ref - target) ** 2).sum().backward()
    torch.testing.assert_close(fast_v.grad, ref_v.grad, atol=1e-7, rtol=1e-7)
    assert ref_v.grad.abs().max() > 1.0  # the scene has real gradients


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32_follows_input_dtype(backend):
    verts, faces = random_mesh(3)
    settings = SoftRasterSettings.from_sigma(1.0, backend=backend)
    out = render_silhouette(verts.float(), faces, K.float(), (H, W), settings)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), naive_render(verts, faces, settings), atol=2e-4, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradcheck_float64(backend):
    settings = SoftRasterSettings.from_sigma(2.0, backend=backend)
    verts, faces = random_mesh(4, n_verts=5, n_faces=3)
    uv = project_points(verts, K)[0].detach().requires_grad_(True)
    z = verts[0, :, 2]
    batch = torch.zeros(len(faces), dtype=torch.long)
    weight = torch.rand(1, 12, 16, generator=torch.Generator().manual_seed(5), dtype=torch.float64)

    def f(uv_):
        return (soft_rasterize(uv_ * 0.6, z, faces, batch, 1, (12, 16), settings) * weight).sum()

    assert torch.autograd.gradcheck(f, (uv,), eps=1e-6, atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_finite_difference_on_one_vertex(backend):
    settings = SoftRasterSettings.from_sigma(2.0, backend=backend)
    verts, faces = random_mesh(6)
    target = torch.zeros(1, H, W, dtype=torch.float64)
    target[:, 5:15, 8:20] = 1

    def loss(v):
        return ((render_silhouette(v, faces, K, (H, W), settings) - target) ** 2).sum()

    v = verts.clone().requires_grad_(True)
    loss(v).backward()
    idx = int(faces[0, 0])
    for axis in range(3):
        step = torch.zeros_like(verts)
        step[0, idx, axis] = 1e-6
        numeric = (loss(verts + step) - loss(verts - step)) / 2e-6
        assert float(v.grad[0, idx, axis]) == pytest.approx(float(numeric), rel=1e-4, abs=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batch_equals_single_renders(backend):
    settings = SoftRasterSettings.from_sigma(1.5, backend=backend)
    verts, faces = random_mesh(7, batch=3)
    Ks = torch.stack([K, K * torch.tensor([[1.1], [0.9], [1.0]], dtype=torch.float64), K])
    batched = render_silhouette(verts, faces, Ks, (H, W), settings)
    for b in range(3):
        single = render_silhouette(verts[b:b + 1], faces, Ks[b], (H, W), settings)
        torch.testing.assert_close(batched[b:b + 1], single, atol=0, rtol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_packed_meshes_of_different_sizes(backend):
    settings = SoftRasterSettings.from_sigma(1.5, backend=backend)
    v0, f0 = random_mesh(8, n_verts=6, n_faces=4)
    v1, f1 = random_mesh(9, n_verts=9, n_faces=7)
    verts = torch.cat([v0[0], v1[0]])
    faces = torch.cat([f0, f1 + 6])
    batch = torch.cat([torch.zeros(6, dtype=torch.long), torch.ones(9, dtype=torch.long)])
    packed = render_silhouette_packed(verts, faces, batch, K, 2, (H, W), settings)
    torch.testing.assert_close(packed[0:1], render_silhouette(v0, f0, K, (H, W), settings))
    torch.testing.assert_close(packed[1:2], render_silhouette(v1, f1, K, (H, W), settings))


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_geometry_gives_valid_output(backend):
    settings = SoftRasterSettings.from_sigma(1.0, backend=backend)
    verts = torch.tensor([[[0.0, 0.0, 0.5], [0.05, 0.0, 0.5], [0.1, 0.0, 0.5],  # collinear: zero area
                           [0.0, 0.0, -0.5], [0.1, 0.1, -0.4], [0.0, 0.1, 0.0],  # behind / at the camera
                           [50.0, 50.0, 1.0], [51.0, 50.0, 1.0], [50.0, 51.0, 1.0]]],  # far off-screen
                         dtype=torch.float64, requires_grad=True)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5], [6, 7, 8], [0, 0, 1]])
    out = render_silhouette(verts, faces, K, (H, W), settings)
    assert torch.isfinite(out).all() and out.abs().max() == 0
    out.sum().backward()
    assert torch.isfinite(verts.grad).all()
    empty = render_silhouette(verts, faces[:0], K, (H, W), settings)
    assert empty.shape == (1, H, W) and empty.abs().max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_face_straddling_near_plane_is_culled(backend):
    settings = SoftRasterSettings.from_sigma(1.0, backend=backend, near_m=0.1)
    verts = torch.tensor([[[-0.1, -0.1, 0.5], [0.1, -0.1, 0.5], [0.0, 0.1, 0.05]]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    assert render_silhouette(verts, faces, K, (H, W), settings).max() == 0
    verts[0, 2, 2] = 0.5
    assert render_silhouette(verts, faces, K, (H, W), settings).max() > 0.99


def test_saturated_interior_is_one_with_zero_gradient():
    settings = SoftRasterSettings.from_sigma(1.0)
    verts = torch.tensor([[[-0.2, -0.2, 0.5], [0.2, -0.2, 0.5], [0.0, 0.3, 0.5]]], dtype=torch.float64,
                         requires_grad=True)
    out = render_silhouette(verts, torch.tensor([[0, 1, 2]]), K, (H, W), settings)
    centre = project_points(verts.detach(), K)[0].mean(0).round().long()
    assert out[0, centre[1], centre[0]] == 1.0
    grad = torch.autograd.grad(out[0, centre[1], centre[0]], verts)[0]
    assert grad.abs().max() == 0


def pixel_centres_inside(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixel centres strictly inside any face (projected vertices ``uv (V, 2)``), numpy, face by
    face (independent of the kernels)."""
    jj, ii = np.meshgrid(np.arange(W), np.arange(H))
    expected = np.zeros((H, W), bool)
    for f in faces:
        c = uv[f]
        area = (c[1, 0] - c[0, 0]) * (c[2, 1] - c[0, 1]) - (c[1, 1] - c[0, 1]) * (c[2, 0] - c[0, 0])
        edges = [np.sign(area) * ((c[(k + 1) % 3, 0] - c[k, 0]) * (ii - c[k, 1]) - (c[(k + 1) % 3, 1] - c[k, 1])
                                  * (jj - c[k, 0])) for k in range(3)]
        expected |= (edges[0] > 0) & (edges[1] > 0) & (edges[2] > 0)
    return expected


@pytest.mark.parametrize("backend", BACKENDS)
def test_hard_render_matches_pixel_centre_test_and_opencv(backend):
    settings = SoftRasterSettings(backend=backend)
    verts, faces = random_mesh(10, n_verts=12, n_faces=10)
    hard = render_hard(verts, faces, K, (H, W), settings)[0].numpy()
    uv = project_points(verts, K)[0].numpy()
    expected = pixel_centres_inside(uv, faces.numpy())
    np.testing.assert_array_equal(hard, expected)
    drawn = np.zeros((H, W), np.uint8)
    for f in faces.numpy():
        cv2.fillConvexPoly(drawn, np.round(uv[f] * 16).astype(np.int32), 1, lineType=cv2.LINE_8, shift=4)
    iou = (hard & (drawn > 0)).sum() / max(1, (hard | (drawn > 0)).sum())
    assert iou > 0.8


@pytest.mark.parametrize("tile_size", [4, 8])
def test_hard_render_of_a_dense_batch_matches_pixel_centre_test(tile_size):
    # many overlapping faces: most tiles fill early and stop reading their bins (the kernel's early exit), tiles
    # cut by the image's edges included; a batch of four binned image by image in parallel
    settings = SoftRasterSettings(backend="numba", tile_size=tile_size)
    verts, faces = random_mesh(11, n_verts=40, n_faces=150, batch=4)
    hard = render_hard(verts, faces, K, (H, W), settings).numpy()
    uv = project_points(verts, K).numpy()
    assert 0.3 < hard.mean() < 0.95  # neither empty nor one full block
    for b in range(4):
        np.testing.assert_array_equal(hard[b], pixel_centres_inside(uv[b], faces.numpy()))


@pytest.mark.parametrize("chunk", [60, 150, 10_000])
def test_hard_render_drawn_a_group_of_images_at_a_time_is_the_same(monkeypatch, chunk):
    # a large batch is set up and drawn a group of whole images at a time (HARD_CHUNK_FACES faces at most, one
    # image when an image has more): 60 splits every image off alone (150 faces each), 150 takes one image per
    # group exactly, 10 000 the whole batch at once; faces not grouped by image are drawn in one pass
    from pipeline.render import _numba_backend

    monkeypatch.setattr(_numba_backend, "HARD_CHUNK_FACES", chunk)
    settings = SoftRasterSettings(backend="numba")
    verts, faces = random_mesh(12, n_verts=40, n_faces=150, batch=5)
    hard = render_hard(verts, faces, K, (H, W), settings).numpy()
    uv = project_points(verts, K).numpy()
    for b in range(5):
        np.testing.assert_array_equal(hard[b], pixel_centres_inside(uv[b], faces.numpy()))
    V = verts.shape[1]
    packed = (faces[None] + torch.arange(5)[:, None, None] * V).reshape(-1, 3)
    order = torch.randperm(len(packed), generator=torch.Generator().manual_seed(0))  # images interleaved
    uv_packed = project_points(verts.reshape(1, -1, 3), K)[0]
    face_batch = torch.arange(5).repeat_interleave(len(faces))
    shuffled = _numba_backend.hard(uv_packed, verts.reshape(-1, 3)[:, 2], packed[order], face_batch[order], 5,
                                   (H, W), settings)
    np.testing.assert_array_equal(shuffled.numpy(), hard)


@pytest.mark.parametrize("grouped", [True, False])
def test_face_bins_match_plain_loops(grouped):
    from pipeline.render._numba_kernels import bin_faces

    rng = np.random.default_rng(0)
    B, F, Hb, Wb, tile = 5, 3000, 60, 80, 8
    i0, j0 = rng.integers(-2, Hb, F), rng.integers(-2, Wb, F)
    bbox = np.stack([i0, i0 + rng.integers(-1, 20, F), j0, j0 + rng.integers(-1, 20, F)], 1)  # some empty
    bbox = np.clip(bbox, 0, [Hb - 1, Hb - 1, Wb - 1, Wb - 1]).astype(np.int64)
    face_batch = rng.integers(0, B, F)
    if grouped:  # faces grouped by image, as packed batches come: binned image by image in parallel
        face_batch = np.sort(face_batch)
    offsets, ids = bin_faces(bbox, face_batch.astype(np.int64), B, Hb, Wb, tile)
    nty, ntx = Hb // tile + (Hb % tile > 0), Wb // tile + (Wb % tile > 0)
    expected = [[] for _ in range(B * nty * ntx)]
    for f in range(F):
        if bbox[f, 0] <= bbox[f, 1] and bbox[f, 2] <= bbox[f, 3]:
            for ty in range(bbox[f, 0] // tile, bbox[f, 1] // tile + 1):
                for tx in range(bbox[f, 2] // tile, bbox[f, 3] // tile + 1):
                    expected[(face_batch[f] * nty + ty) * ntx + tx].append(f)
    assert len(offsets) == len(expected) + 1
    for k, faces_in_bin in enumerate(expected):
        assert ids[offsets[k]:offsets[k + 1]].tolist() == faces_in_bin


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("saturation", [20.0, 2.0])
def test_one_pass_gives_the_hard_silhouette_and_the_same_soft_one(backend, saturation):
    # saturation 2: pixels inside two faces saturate before the rest of the bin is seen, so the hard value must
    # still be looked up past saturation (the kernel's second branch)
    settings = SoftRasterSettings.from_sigma(1.0, backend=backend, saturation=saturation)
    for seed in range(6):
        verts, faces = random_mesh(20 + seed, n_verts=14, n_faces=25, batch=2)
        verts_a = verts.clone().requires_grad_(True)
        verts_b = verts.clone().requires_grad_(True)
        V = verts.shape[1]
        packed = (faces[None] + torch.arange(2)[:, None, None] * V).reshape(-1, 3)
        batch = torch.arange(2).repeat_interleave(V)
        soft, hard = render_silhouette_packed(verts_a.reshape(-1, 3), packed, batch, K, 2, (H, W), settings,
                                              return_hard=True)
        alone = render_silhouette_packed(verts_b.reshape(-1, 3), packed, batch, K, 2, (H, W), settings)
        assert hard.dtype == torch.bool and hard.shape == (2, H, W)
        assert torch.equal(hard, render_hard(verts.detach(), faces, K, (H, W), settings))
        assert 0 < int(hard.sum()) < hard.numel()
        assert torch.equal(soft, alone)
        soft.square().sum().backward()
        alone.square().sum().backward()
        assert torch.equal(verts_a.grad, verts_b.grad)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_straight_through_value_is_the_hard_silhouette_and_its_gradient_the_soft_one(backend, dtype):
    settings = SoftRasterSettings.from_sigma(1.0, backend=backend)
    verts, faces = random_mesh(31, n_verts=14, n_faces=25, batch=2)
    verts = verts.to(dtype)
    V = verts.shape[1]
    packed = (faces[None] + torch.arange(2)[:, None, None] * V).reshape(-1, 3)
    batch = torch.arange(2).repeat_interleave(V)
    weight = torch.rand(2, H, W, generator=torch.Generator().manual_seed(1), dtype=dtype)
    verts_a = verts.clone().reshape(-1, 3).requires_grad_(True)
    verts_b = verts.clone().reshape(-1, 3).requires_grad_(True)
    value, hard = render_silhouette_packed(verts_a, packed, batch, K, 2, (H, W), settings, return_hard=True,
                                           straight_through=True)
    soft = render_silhouette_packed(verts_b, packed, batch, K, 2, (H, W), settings)
    assert value.dtype == dtype and torch.equal(value, hard.to(dtype))  # exactly the estimator's s + (h - s)
    assert torch.equal(value, soft + (hard.to(dtype) - soft).detach())
    assert 0 < float(value.detach().mean()) < 1 and not torch.equal(value, soft)
    (value * weight).sum().backward()
    (soft * weight).sum().backward()
    assert verts_a.grad.abs().sum() > 0 and torch.equal(verts_a.grad, verts_b.grad)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CPU/CUDA parity needs a CUDA device")
def test_cpu_cuda_parity():
    settings = SoftRasterSettings.from_sigma(1.5)
    verts, faces = random_mesh(11, batch=2)
    cpu_v = verts.clone().requires_grad_(True)
    gpu_v = verts.cuda().requires_grad_(True)
    cpu = render_silhouette(cpu_v, faces, K, (H, W), settings)
    gpu = render_silhouette(gpu_v, faces.cuda(), K.cuda(), (H, W), settings)
    torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=0)
    cpu.square().sum().backward()
    gpu.square().sum().backward()
    torch.testing.assert_close(gpu_v.grad.cpu(), cpu_v.grad, atol=1e-7, rtol=1e-7)


def test_bad_input_names_the_problem():
    verts, faces = random_mesh(12)
    with pytest.raises(ShapeError, match=r"verts_cam: expected shape \(B, V, 3\)"):
        render_silhouette(verts[0], faces, K, (H, W))
    with pytest.raises(ShapeError, match=r"faces: vertex indices must lie in \[0, 9\)"):
        render_silhouette(verts, faces + 20, K, (H, W))
    with pytest.raises(ShapeError, match="faces: expected an int64"):
        render_silhouette(verts, faces.float(), K, (H, W))
    bad = verts.clone()
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ShapeError, match="NaN"):
        render_silhouette(bad, faces, K, (H, W))
    with pytest.raises(ShapeError, match=r"K: expected shape \(2, 3, 3\)"):
        render_silhouette(verts.expand(2, -1, -1), faces, K[None], (H, W))
    with pytest.raises(ConfigError, match="image_size"):
        render_silhouette(verts, faces, K, (0, W))


def test_settings_conversion_and_validation():
    paper = SoftRasterSettings.from_pytorch3d(1e-4, np.log(1 / 1e-4 - 1) * 1e-4, (480, 640))
    assert paper.sigma_px2 == pytest.approx(5.76)
    assert paper.cutoff_px == pytest.approx(7.2836, abs=1e-4)
    assert SoftRasterSettings.from_pytorch3d(1e-4, np.log(1 / 1e-4 - 1) * 1e-4, (256, 256)).cutoff_px == \
        pytest.approx(3.8846, abs=1e-4)
    assert SoftRasterSettings() == SoftRasterSettings.from_sigma(5.76)
    with pytest.raises(ConfigError, match="backend: expected one of 'auto', 'numba', 'torch'"):
        SoftRasterSettings(backend="cuda")
    with pytest.raises(ConfigError, match="sigma_px2"):
        SoftRasterSettings(sigma_px2=0.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_back_face_culling_keeps_the_faces_turned_to_the_camera(backend):
    # A closed tube seen obliquely: culling by screen winding must draw exactly the faces whose outward normal
    # points at the camera (n . c < 0, camera frame), chosen here independently in 3D and rendered without culling.
    from pipeline.shapes.tube import bezier_tube_vertices, tube_faces

    control = torch.tensor([[[-0.06, 0.02, 0.50], [0.00, -0.05, 0.56], [0.07, 0.03, 0.62]]], dtype=torch.float64)
    verts = bezier_tube_vertices(control, torch.full((1, 6), 0.012, dtype=torch.float64), n_angles=8)
    faces = tube_faces(6, 8)
    corners = verts[0, faces]  # (F, 3, 3)
    normal = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=-1)
    front = faces[(normal * corners.sum(1)).sum(-1) < 0]
    assert 0.3 * len(faces) < len(front) < 0.7 * len(faces)
    settings = SoftRasterSettings.from_sigma(0.5, backend=backend, saturation=60.0)
    culled_v = verts.clone().requires_grad_(True)
    chosen_v = verts.clone().requires_grad_(True)
    culled = render_silhouette(culled_v, faces, K, (H, W), SoftRasterSettings.from_sigma(
        0.5, backend=backend, saturation=60.0, cull_back_faces=True))
    chosen = render_silhouette(chosen_v, front, K, (H, W), settings)
    everything = render_silhouette(verts, faces, K, (H, W), settings)
    torch.testing.assert_close(culled, chosen, atol=1e-12, rtol=0)
    assert float((everything - culled.detach()).abs().max()) > 0.05  # the back faces do change the soft image
    culled.square().sum().backward()
    chosen.square().sum().backward()
    torch.testing.assert_close(culled_v.grad, chosen_v.grad, atol=1e-9, rtol=1e-9)
    naive = naive_soft_rasterize(project_points(verts, K)[0], verts[0, :, 2], faces,
                                 torch.zeros(len(faces), dtype=torch.int64), 1, (H, W),
                                 SoftRasterSettings.from_sigma(0.5, saturation=60.0, cull_back_faces=True))
    torch.testing.assert_close(culled.detach(), naive, atol=1e-10, rtol=0)
    with pytest.raises(ConfigError, match="cull_back_faces: expected True or False"):
        SoftRasterSettings(cull_back_faces=1)


def test_forward_kernel_writes_every_pixel_it_returns():
    # The CPU backend hands the kernel uninitialised buffers: every pixel of the silhouette and of the hard image,
    # and 1 - S in every tile a face touches (where the backward reads), must be written, not left as found.
    from pipeline.render import _numba_backend
    from pipeline.render import _numba_kernels as kernels

    verts, faces = random_mesh(5, n_verts=12, n_faces=10, batch=2)
    verts = verts * torch.tensor([0.3, 0.3, 1.0], dtype=torch.float64)  # a part of the image only
    settings = SoftRasterSettings.from_sigma(1.0, tile_size=4)
    V = verts.shape[1]
    packed = (faces[None] + torch.arange(2)[:, None, None] * V).reshape(-1, 3)
    uv = project_points(verts.reshape(1, -1, 3), K)[0]
    fe, bbox, offsets, ids, _, _ = _numba_backend._setup(uv, verts.reshape(-1, 3)[:, 2], packed,
                                                          torch.arange(2).repeat_interleave(len(faces)), 2, (H, W),
                                                          settings, settings.cutoff_px)
    silhouette = np.full((2, H, W), np.nan)
    one_minus = np.full((2, H, W), np.nan)
    hard = np.ones((2, H, W), np.bool_)
    kernels.soft_forward(fe, bbox, offsets, ids, 2, H, W, settings.tile_size, 1.0 / settings.sigma_px2,
                         settings.cutoff_px, settings.saturation, 2, silhouette, one_minus, hard, True, False)
    expected = naive_render(verts, faces, settings).numpy()
    np.testing.assert_allclose(silhouette, expected, atol=1e-9)
    assert np.array_equal(hard, render_hard(verts, faces, K, (H, W), settings).numpy())
    touched = np.repeat(np.repeat((np.diff(offsets) > 0).reshape(2, -1, (W + 3) // 4), 4, 1), 4, 2)[:, :H, :W]
    assert 0 < touched.mean() < 1
    assert np.isfinite(one_minus[touched]).all()
    counted = (expected > 0) & (1 - expected >= np.exp(-settings.saturation))  # 0 where none counts or saturated
    np.testing.assert_allclose(one_minus[touched], np.where(counted, 1 - expected, 0)[touched], atol=1e-9)
    # the straight-through value: the hard silhouette in place of S, S's 1 - S kept for the backward
    value, one_minus_st, hard_st = np.full((2, H, W), np.nan), np.full((2, H, W), np.nan), np.ones((2, H, W), bool)
    kernels.soft_forward(fe, bbox, offsets, ids, 2, H, W, settings.tile_size, 1.0 / settings.sigma_px2,
                         settings.cutoff_px, settings.saturation, 2, value, one_minus_st, hard_st, True, True)
    assert np.array_equal(value, hard.astype(float)) and np.array_equal(hard_st, hard)
    assert np.array_equal(one_minus_st[touched], one_minus[touched])
