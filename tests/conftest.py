"""Shared test fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

if os.environ.get("PYTEST_XDIST_WORKER"):
    # `make test` runs one pytest-xdist worker per core (at most 4): one thread each for torch and the renderer's
    # numba pool, set before either is imported, so that the workers do not oversubscribe the cores (an
    # oversubscribed numba region waits for its slowest thread; docs/tracking.md, "Load matters ...").
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ.setdefault(_name, "1")


def shared_dir() -> Path:
    """``../shared`` beside the checkout (or $PIPELINE_SHARED_DIR): design docs and reference outputs."""
    return Path(os.environ.get("PIPELINE_SHARED_DIR", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def pytorch3d_reference_dir() -> Path:
    """Folder of PyTorch3D reference outputs; skips outside CI when absent, fails in CI (it must run there)."""
    path = shared_dir() / "reference" / "pytorch3d"
    if not path.is_dir():
        reason = f"PyTorch3D reference outputs not found at {path} (they live in ../shared beside the checkout)"
        if os.environ.get("CI"):
            pytest.fail(reason + "; CI must run these tests")
        pytest.skip(reason)
    return path
