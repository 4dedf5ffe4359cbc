import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

# A fresh process: numba's workers start at its first render, which is what the fits must not be changed by.
SCRIPT = """
import torch
from pipeline.render import render_hard, render_silhouette, single_torch_thread

verts = torch.tensor([[[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.0, 0.1, 1.0]]], dtype=torch.float64)
faces = torch.tensor([[0, 1, 2]])
K = torch.tensor([[100.0, 0.0, 31.5], [0.0, 100.0, 23.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
torch.set_num_threads(3)
with single_torch_thread():
    render_hard(verts, faces, K, (48, 64))
    render_silhouette(verts, faces, K, (48, 64))
    inside = torch.get_num_threads()
print(inside, torch.get_num_threads())
"""


def test_single_torch_thread_holds_through_the_renderers_first_call():
    """numba's OpenMP workers, started by a process's first render, reset the OpenMP thread count that torch reads;
    ``single_torch_thread`` starts them first, so torch stays on one thread for the whole block (and a process's
    first fit rounds like every later one) and gets the caller's count back afterwards."""
    env = dict(os.environ, NUMBA_NUM_THREADS="2", PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, cwd=REPO,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", "3"]
