"""Settings of the soft silhouette rasterizer, in pixel units."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.checks import check_choice, check_image_size, check_positive
from pipeline.errors import ConfigError

BACKENDS = ("auto", "numba", "torch")


def cutoff_from_sigma(sigma_px2: float, eps: float = 1e-4) -> float:
    """Cut-off radius (px) where an outside face's probability has fallen to ``eps``.

    Convention: SoftRas / PyTorch3D blur radius ``ln(1/eps - 1) * sigma``, i.e. ``sigmoid(-r^2 / sigma) = eps``;
    returned as a distance ``r = sqrt(ln(1/eps - 1) * sigma_px2)`` in pixels.
    """
    check_positive(sigma_px2, "sigma_px2")
    if not 0.0 < eps < 0.5:
        raise ConfigError(f"eps: expected a probability in (0, 0.5), got {eps!r}")
    return math.sqrt(math.log(1.0 / eps - 1.0) * sigma_px2)


@dataclass(frozen=True, kw_only=True)
class SoftRasterSettings:
    """How soft the silhouette is and where the work stops.

    For pixel centre ``p`` and projected triangle ``f`` let ``d`` be the distance from ``p`` to the triangle's
    boundary, negative inside. The face's probability is ``sigmoid(-sign(d) d^2 / sigma_px2)`` and it counts when
    ``p`` is inside or ``d < cutoff_px``; ``S(p) = 1 - prod_f (1 - prob_f)``.

    Fields:
        sigma_px2: sharpness, squared pixels. PyTorch3D's NDC ``sigma`` is ``sigma_px2 / s^2`` with
            ``s = min(H, W) / 2``; the default 5.76 is the paper's ``sigma = 1e-4`` at 640x480.
        cutoff_px: faces farther than this outside a pixel are ignored (PyTorch3D: ``sqrt(blur_radius) * s``).
            The default is ``cutoff_from_sigma(5.76)`` = 7.28 px, where an outside face's probability is 1e-4.
        near_m: faces with a vertex nearer than this depth (metres, camera z) are culled.
        min_face_area_px2: faces whose projected area is below this are skipped (degenerate triangles).
        cull_back_faces: skip the faces turned away from the camera: those whose corners, projected, run
            clockwise on the screen (u right, v down; ``(c1 - c0) x (c2 - c0) > 0``). For a face in front of the
            camera that is exactly ``n . c > 0`` (outward normal ``n = (c1 - c0) x (c2 - c0)``, a corner ``c``,
            camera frame): a closed mesh wound outward keeps the faces that cover its silhouette, half the work.
        saturation: a pixel whose ``-log(1 - S)`` exceeds this is saturated (``1 - S < e^-saturation``): its
            remaining faces are skipped and its gradient is zero. The default 20 keeps ``1 - S < 2e-9``.
        tile_size: side of the square image tiles faces are binned into (pixels).
        backend: "numba" (compiled CPU kernels), "torch" (tensor ops, any device) or "auto" (numba for CPU
            tensors, torch otherwise).
        max_pairs_per_chunk: memory bound of the torch backend: (pixel, face) candidates processed at once.
    """

    sigma_px2: float = 5.76
    cutoff_px: float = 7.283610678350463
    near_m: float = 1e-3
    min_face_area_px2: float = 1e-6
    cull_back_faces: bool = False
    saturation: float = 20.0
    tile_size: int = 8
    backend: str = "auto"
    max_pairs_per_chunk: int = 4_000_000

    def __post_init__(self) -> None:
        check_positive(self.sigma_px2, "sigma_px2")
        check_positive(self.cutoff_px, "cutoff_px", allow_zero=True)
        check_positive(self.near_m, "near_m")
        check_positive(self.min_face_area_px2, "min_face_area_px2", allow_zero=True)
        check_positive(self.saturation, "saturation")
        if not isinstance(self.cull_back_faces, bool):
            raise ConfigError(f"cull_back_faces: expected True or False, got {self.cull_back_faces!r}")
        check_choice(self.backend, BACKENDS, "backend")
        if not isinstance(self.tile_size, int) or not 1 <= self.tile_size <= 256:
            raise ConfigError(f"tile_size: expected an int in [1, 256], got {self.tile_size!r}")
        if not isinstance(self.max_pairs_per_chunk, int) or self.max_pairs_per_chunk < 1024:
            raise ConfigError(f"max_pairs_per_chunk: expected an int >= 1024, got {self.max_pairs_per_chunk!r}")

    @classmethod
    def from_sigma(cls, sigma_px2: float, *, eps: float = 1e-4, **kwargs) -> "SoftRasterSettings":
        """Settings with the cut-off where an outside face's probability falls to ``eps``."""
        return cls(sigma_px2=sigma_px2, cutoff_px=cutoff_from_sigma(sigma_px2, eps), **kwargs)

    @classmethod
    def from_pytorch3d(
        cls, sigma: float, blur_radius: float, image_size: tuple[int, int], **kwargs
    ) -> "SoftRasterSettings":
        """Convert PyTorch3D's NDC settings (``sigma``, ``blur_radius``, both squared NDC units) to pixels."""
        H, W = check_image_size(image_size)
        check_positive(sigma, "sigma")
        check_positive(blur_radius, "blur_radius", allow_zero=True)
        s = min(H, W) / 2.0
        return cls(sigma_px2=sigma * s * s, cutoff_px=math.sqrt(blur_radius) * s, **kwargs)
