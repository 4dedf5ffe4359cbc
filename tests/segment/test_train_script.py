"""``models/segmenters/train.py``'s fine-tuning start: the state dict an export saves beside ``model.onnx``, and for
the shipped model (which has none) its ONNX weights read back into the torch network (batch norms folded by the
export), which give the same logits as onnxruntime."""

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


def test_export_saves_the_state_dict_and_init_starts_from_it(train_module, tmp_path):
    torch.manual_seed(0)
    trained = train_module.RobotDeepLab(width=16)
    with torch.no_grad():  # batch-norm statistics the ONNX export would fold away
        for m in trained.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.running_mean.uniform_(-0.5, 0.5)
                m.running_var.uniform_(0.5, 2.0)
    train_module.export_onnx(trained, tmp_path / "model.onnx")
    assert (tmp_path / "model.onnx").is_file() and (tmp_path / train_module.STATE_DICT).is_file()
    model = train_module.RobotDeepLab(width=16)
    train_module.load_init(model, tmp_path)
    for (name, got), expected in zip(model.state_dict().items(), trained.state_dict().values()):
        assert torch.equal(got, expected), name


def test_init_from_the_shipped_model_reads_its_onnx_weights(train_module):
    assert not (SHIPPED / train_module.STATE_DICT).exists()
    from_init, from_onnx = train_module.RobotDeepLab(), train_module.RobotDeepLab()
    train_module.load_init(from_init, SHIPPED / "model.onnx")
    train_module.load_onnx_weights(from_onnx, SHIPPED)
    for (name, got), expected in zip(from_init.state_dict().items(), from_onnx.state_dict().values()):
        assert torch.equal(got, expected), name
