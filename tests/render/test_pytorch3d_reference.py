"""Our rasterizer against PyTorch3D's SoftSilhouetteShader outputs (../shared/reference/pytorch3d/README.md).

Rules of that README: where PyTorch3D kept fewer than ``faces_per_pixel`` faces, |alpha_ours - alpha| <= 2e-3;
where it truncated, alpha_ours >= alpha - 2e-3 (more faces only raise alpha); gradient cosine >= 0.999 on the
ctrnet files. On chainB_640x480_paper our untruncated gradient reaches a cosine of 0.9987, not 0.999: PyTorch3D
drops faces at 1227 pixels there (alpha down to 0.63 where ours is 1), and those pixels carry gradient in its
result that an untruncated renderer does not have. That file is held to 0.998 and the gap is reported in the README;
``test_chain_paper_gradient_gap_is_truncation`` shows where the gap lives: on the vertices whose faces count at no
truncated pixel our gradient equals PyTorch3D's (relative error 1e-5), and all of the difference sits on the
vertices whose faces reach truncated pixels.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from pipeline.render import SoftRasterSettings, render_silhouette

FILES = ["tubeA_256_paper", "tubeA_256_ctrnet", "tubeA_640x480_paper", "tubeA_640x480_ctrnet",
         "chainB_640x480_paper", "chainB_640x480_ctrnet"]
MIN_COSINE = {"tubeA_256_ctrnet": 0.999, "tubeA_640x480_ctrnet": 0.999, "chainB_640x480_ctrnet": 0.999,
              "chainB_640x480_paper": 0.998}


def run_reference(path, backend: str):
    ref = np.load(path)
    H, W = (int(s) for s in ref["image_size"])
    settings = SoftRasterSettings.from_pytorch3d(float(ref["sigma"]), float(ref["blur_radius"]), (H, W),
                                                 backend=backend)
    verts = torch.tensor(ref["verts"])[None].requires_grad_(True)
    alpha = render_silhouette(verts, torch.tensor(ref["faces"]), torch.tensor(ref["K"], dtype=torch.float32),
                              (H, W), settings)[0]
    loss = ((alpha - torch.tensor(ref["M"], dtype=torch.float32)) ** 2).sum()
    loss.backward()
    return ref, alpha.detach().numpy(), verts.grad[0].numpy()


@pytest.mark.parametrize("name", FILES)
def test_matches_pytorch3d(pytorch3d_reference_dir, name):
    ref, alpha, grad = run_reference(pytorch3d_reference_dir / f"{name}.npz", "numba")
    truncated = ref["n_faces_hit"] >= int(ref["faces_per_pixel"])
    assert np.abs(alpha - ref["alpha"])[~truncated].max() <= 2e-3
    if truncated.any():
        assert (ref["alpha"] - alpha)[truncated].max() <= 2e-3
    assert ((alpha > 0.5) == (ref["alpha"] > 0.5))[~truncated].mean() > 0.999  # orientation: no flips
    if name in MIN_COSINE:
        ref_grad = ref["grad"].astype(np.float64)
        cosine = (grad * ref_grad).sum() / np.linalg.norm(grad) / np.linalg.norm(ref_grad)
        assert cosine >= MIN_COSINE[name]


@pytest.mark.parametrize("name", ["tubeA_256_ctrnet", "chainB_640x480_ctrnet"])
def test_torch_backend_matches_pytorch3d(pytorch3d_reference_dir, name):
    ref, alpha, grad = run_reference(pytorch3d_reference_dir / f"{name}.npz", "torch")
    assert np.abs(alpha - ref["alpha"]).max() <= 2e-3
    ref_grad = ref["grad"].astype(np.float64)
    assert (grad * ref_grad).sum() / np.linalg.norm(grad) / np.linalg.norm(ref_grad) >= 0.999


def test_chain_paper_gradient_gap_is_truncation(pytorch3d_reference_dir):
    ref = np.load(pytorch3d_reference_dir / "chainB_640x480_paper.npz")
    H, W = (int(s) for s in ref["image_size"])
    # no saturation stop: every (pixel, face) pair that counts must carry gradient for the "touches" test
    settings = dataclasses.replace(
        SoftRasterSettings.from_pytorch3d(float(ref["sigma"]), float(ref["blur_radius"]), (H, W)), saturation=700.0)
    faces, K = torch.tensor(ref["faces"]), torch.tensor(ref["K"], dtype=torch.float64)
    truncated = torch.tensor(ref["n_faces_hit"] >= int(ref["faces_per_pixel"]), dtype=torch.float64)
    verts = torch.tensor(ref["verts"], dtype=torch.float64)[None].requires_grad_(True)
    alpha = render_silhouette(verts, faces, K, (H, W), settings)[0]
    grad, = torch.autograd.grad(((alpha - torch.tensor(ref["M"], dtype=torch.float64)) ** 2).sum(), verts,
                                retain_graph=True)
    reach, = torch.autograd.grad((alpha * truncated).sum(), verts)  # non-zero iff a face counts at a truncated px
    touches = reach[0].abs().sum(1) > 0
    ref_grad = torch.tensor(ref["grad"], dtype=torch.float64)
    residual = ref_grad - grad[0]
    assert 0 < int((~touches).sum()) < len(touches)
    untouched = ref_grad[~touches].norm()
    assert residual[~touches].norm() <= 1e-4 * untouched  # measured 1.3e-5
    assert residual[touches].norm() > 0.03 * ref_grad.norm()  # measured 0.052 (the whole gap)
