"""``models/segmenters/train.py``'s fine-tuning start: the shipped ONNX model's weights read back into the torch
network (batch norms folded by the export) give the same logits as onnxruntime."""

import importlib.util
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
import torch

REPO = Path(__file__).resolve().parents[2]
SHIPPED = REPO / "models" / "segmenters" / "robot_deeplab"


@pytest.fixture(scope="module")
def train_module():
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("NUMBA_NUM_THREADS", raising=False)  # the script sets it; give the environment back afterwards
        spec = importlib.util.spec_from_file_location("robot_deeplab_train", REPO / "models/segmenters/train.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    return module


def test_onnx_module_path(train_module):
    path = train_module.onnx_module_path
    assert path("/aspp/branches.1/branches.1.0/branches.1.0.0/Conv") == "aspp.branches.1.0.0"
    assert path("/aspp/pool/pool.1/Conv") == "aspp.pool.1"
    assert path("/stem/stem.0/Conv") == "stem.0" and path("/classifier/Conv") == "classifier"


def test_shipped_weights_load_back_into_the_network(train_module):
    model = train_module.RobotDeepLab()
    train_module.load_onnx_weights(model, SHIPPED)
    x = torch.randn(2, 3, 96, 128, generator=torch.Generator().manual_seed(0))
    session = ort.InferenceSession(str(SHIPPED / "model.onnx"), providers=["CPUExecutionProvider"])
    expected = np.concatenate([session.run(None, {"image": x[i : i + 1].numpy()})[0] for i in range(2)])
    model.eval()
    with torch.no_grad():
        np.testing.assert_allclose(model(x).numpy(), expected, atol=1e-4 * np.abs(expected).max())
    model.train()
    train_module.freeze_batch_norm(model)  # fine-tuning mode: the same function (fixed statistics)
    with torch.no_grad():
        np.testing.assert_allclose(model(x).numpy(), expected, atol=1e-4 * np.abs(expected).max())
    with pytest.raises(train_module.ConfigError, match="does not match this architecture"):
        train_module.load_onnx_weights(train_module.RobotDeepLab(width=32), SHIPPED)
