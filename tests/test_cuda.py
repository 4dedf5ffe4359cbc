"""The CUDA path against the CPU path: renderer, tube, frames, losses, distance map and FK on a CUDA device.

Skipped where torch sees no CUDA device (CI has none); run on a GPU machine with ``pytest tests/test_cuda.py``.
Each test computes the same thing from the same inputs on the CPU (the default, compiled numba kernels where
there are some) and on CUDA (the torch backends), and compares values and gradients; the renderer is also held to
PyTorch3D's reference outputs on CUDA, with the rules of ``tests/render/test_pytorch3d_reference.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.camera import project_points
from pipeline.losses import appearance_loss, distance_loss, keypoint_loss, mask_loss
from pipeline.preprocess import distance_to_mask
from pipeline.render import SoftRasterSettings, render_hard, render_silhouette
from pipeline.robots import load_robot
from pipeline.shapes.bezier import bezier_points
from pipeline.shapes.tube import bezier_tube_vertices, taper_radii, tube_faces

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

K = torch.tensor([[300.0, 0.0, 79.5], [0.0, 300.0, 59.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
H, W = 120, 160


def control_points(dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """(2, 4, 3) two cubic centrelines in front of the camera, one bending both ways, one straight."""
    return torch.tensor([[[0.0, 0.02, 0.50], [0.03, 0.0, 0.53], [0.05, -0.03, 0.55], [0.08, -0.01, 0.60]],
                         [[-0.05, 0.0, 0.5], [-0.02, 0.0, 0.5], [0.01, 0.0, 0.5], [0.04, 0.0, 0.5]]], dtype=dtype)


def tube(cp: torch.Tensor, n_rings: int = 24, n_angles: int = 12) -> tuple[torch.Tensor, torch.Tensor]:
    radii = taper_radii(0.012, 0.006, n_rings, dtype=cp.dtype, device=cp.device).expand(cp.shape[0], -1)
    return bezier_tube_vertices(cp, radii, n_angles), tube_faces(n_rings, n_angles, device=cp.device)


def test_tube_and_frames_match_the_cpu_values_and_gradients():
    cpu = control_points().requires_grad_(True)
    gpu = control_points().cuda().requires_grad_(True)
    verts_cpu, faces_cpu = tube(cpu)
    verts_gpu, faces_gpu = tube(gpu)
    assert verts_gpu.device.type == "cuda" and faces_gpu.device.type == "cuda"
    assert torch.equal(faces_gpu.cpu(), faces_cpu)
    torch.testing.assert_close(verts_gpu.cpu(), verts_cpu, atol=1e-12, rtol=1e-9)
    weights = torch.linspace(-1.0, 1.0, verts_cpu.numel(), dtype=torch.float64).reshape(verts_cpu.shape)
    (verts_cpu * weights).sum().backward()
    (verts_gpu * weights.cuda()).sum().backward()
    torch.testing.assert_close(gpu.grad.cpu(), cpu.grad, atol=1e-9, rtol=1e-7)


def test_tube_silhouette_matches_the_cpu_values_and_gradients():
    """The whole soft arm's forward chain (Bezier -> frames -> tube -> projection -> soft silhouette -> mask loss)."""
    settings = SoftRasterSettings.from_sigma(1.0)
    target = torch.zeros(H, W, dtype=torch.float64)
    target[40:80, 60:120] = 1.0
    losses, grads = [], []
    for device in ("cpu", "cuda"):
        cp = control_points().to(device).requires_grad_(True)
        verts, faces = tube(cp)
        silhouette = render_silhouette(verts, faces, K.to(device), (H, W), settings)
        assert silhouette.device.type == device
        loss = mask_loss(silhouette, target.to(device)).sum()
        loss.backward()
        losses.append(loss.detach().cpu())
        grads.append(cp.grad.cpu())
    torch.testing.assert_close(losses[1], losses[0], atol=1e-8, rtol=1e-9)
    torch.testing.assert_close(grads[1], grads[0], atol=1e-7, rtol=1e-6)
    assert grads[0].abs().sum() > 0


def test_hard_silhouette_matches_the_cpu():
    verts, faces = tube(control_points())
    settings = SoftRasterSettings()
    cpu = render_hard(verts, faces, K, (H, W), settings)
    gpu = render_hard(verts.cuda(), faces.cuda(), K.cuda(), (H, W), settings)
    assert 0 < int(cpu.sum()) < cpu.numel()
    assert torch.equal(gpu.cpu(), cpu)


@pytest.mark.parametrize("name", ["tubeA_256_paper", "tubeA_256_ctrnet", "tubeA_640x480_paper",
                                  "tubeA_640x480_ctrnet", "chainB_640x480_paper", "chainB_640x480_ctrnet"])
def test_cuda_renderer_matches_pytorch3d(pytorch3d_reference_dir, name):
    ref = np.load(pytorch3d_reference_dir / f"{name}.npz")
    rows, cols = (int(s) for s in ref["image_size"])
    settings = SoftRasterSettings.from_pytorch3d(float(ref["sigma"]), float(ref["blur_radius"]), (rows, cols))
    verts = torch.tensor(ref["verts"], device="cuda")[None].requires_grad_(True)
    alpha = render_silhouette(verts, torch.tensor(ref["faces"], device="cuda"),
                              torch.tensor(ref["K"], dtype=torch.float32, device="cuda"), (rows, cols), settings)[0]
    ((alpha - torch.tensor(ref["M"], dtype=torch.float32, device="cuda")) ** 2).sum().backward()
    alpha, grad = alpha.detach().cpu().numpy(), verts.grad[0].cpu().numpy().astype(np.float64)
    truncated = ref["n_faces_hit"] >= int(ref["faces_per_pixel"])
    assert np.abs(alpha - ref["alpha"])[~truncated].max() <= 2e-3
    if truncated.any():
        assert (ref["alpha"] - alpha)[truncated].max() <= 2e-3
    min_cosine = {"chainB_640x480_paper": 0.998}.get(name, 0.999 if "ctrnet" in name else None)
    if min_cosine is not None:
        ref_grad = ref["grad"].astype(np.float64)
        assert (grad * ref_grad).sum() / np.linalg.norm(grad) / np.linalg.norm(ref_grad) >= min_cosine


def test_render_gradcheck_on_cuda():
    """The torch backend's backward on CUDA sums the (pixel, face) terms with atomic adds, whose order varies from
    run to run: it is exact to float64 rounding but not bit-reproducible (``nondet_tol``; measured on an H200)."""
    cp = control_points()[:1]
    verts, faces = tube(cp, n_rings=5, n_angles=6)
    small_k = torch.tensor([[60.0, 0.0, 15.5], [0.0, 60.0, 11.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    settings = SoftRasterSettings.from_sigma(2.0)
    verts = verts.detach().cuda().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v: render_silhouette(v, faces.cuda(), small_k.cuda(), (24, 32), settings), (verts,),
        eps=1e-7, atol=1e-5, nondet_tol=1e-12)


def test_losses_projection_and_distance_map_follow_the_device():
    g = torch.Generator().manual_seed(3)
    silhouette = torch.rand(2, H, W, generator=g, dtype=torch.float64)
    mask = torch.zeros(H, W, dtype=torch.bool)
    mask[30:70, 50:90] = True
    distance = distance_to_mask(mask)
    distance_gpu = distance_to_mask(mask.cuda())
    assert distance_gpu.device.type == "cuda"
    torch.testing.assert_close(distance_gpu.cpu(), distance)
    target = mask.to(torch.float64)
    for fn, second in ((mask_loss, target), (distance_loss, distance.to(torch.float64)),
                       (appearance_loss, target)):
        cpu = fn(silhouette, second)
        gpu = fn(silhouette.cuda(), second.cuda())
        assert gpu.device.type == "cuda"
        torch.testing.assert_close(gpu.cpu(), cpu, atol=1e-9, rtol=1e-12)
    points = bezier_points(control_points(), torch.linspace(0, 1, 5, dtype=torch.float64))  # (2, 5, 3)
    uv = project_points(points, K)
    uv_gpu = project_points(points.cuda(), K.cuda())
    torch.testing.assert_close(uv_gpu.cpu(), uv)
    torch.testing.assert_close(keypoint_loss(uv_gpu, uv_gpu.flip(1)).cpu(), keypoint_loss(uv, uv.flip(1)))


def test_manipulator_mesh_follows_the_joint_angles_device():
    """FK (pytorch-kinematics) and the link meshes on CUDA: the same vertices and joint gradients as on the CPU."""
    model = load_robot(Path(__file__).resolve().parents[1] / "models/robots/toy_arm/toy_arm.urdf", "base_link")
    g = torch.Generator().manual_seed(5)
    lower = model.joint_lower.clamp(min=-3.0)
    upper = model.joint_upper.clamp(max=3.0)
    q = lower + (upper - lower) * torch.rand(2, len(model.joint_names), generator=g, dtype=torch.float64)
    results = []
    for device in ("cpu", "cuda"):
        angles = q.to(device).detach().requires_grad_(True)  # a leaf on either device
        verts = model.mesh_in_root(angles)
        assert verts.device.type == device
        (verts * verts).sum().backward()
        results.append((verts.detach().cpu(), angles.grad.cpu()))
    torch.testing.assert_close(results[1][0], results[0][0], atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(results[1][1], results[0][1], atol=1e-9, rtol=1e-9)
