"""Differentiable soft silhouette rasterizer (our own; PyTorch3D's SoftSilhouetteShader without truncation)."""

from pipeline.render.rasterize import (render_hard, render_silhouette, render_silhouette_packed, single_torch_thread,
                                       soft_rasterize)
from pipeline.render.settings import SoftRasterSettings, cutoff_from_sigma

__all__ = [
    "SoftRasterSettings",
    "cutoff_from_sigma",
    "render_hard",
    "render_silhouette",
    "render_silhouette_packed",
    "single_torch_thread",
    "soft_rasterize",
]
