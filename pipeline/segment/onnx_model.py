"""ONNX segmenter: a user-exported DeepLab-style network run by onnxruntime.

A model is a folder holding ``model.onnx`` and ``meta.json``; a bare name ``NAME`` means the folder
``models/segmenters/NAME/`` of this repository (the shipped model is ``robot_deeplab``). ``meta.json``:

    {
      "input_size": [H, W] | "dynamic",   # fixed: the image is resized (stretched) to W x H; dynamic: fed as it is,
      "size_multiple": 16,                # optional, dynamic only: pad bottom/right to a multiple (default 1)
      "max_side": 960,                    # optional, dynamic only: a larger image is shrunk (area) to this longer
                                          #   side first (the scale the network knows; default 0: never)
      "channel_order": "rgb" | "bgr",     # channel order the network expects
      "scale": 0.00392156862745098,       # x = (pixel * scale - mean) / std, per channel in the network's order
      "mean": [m0, m1, m2],
      "std": [s0, s1, s2],
      "output": "logits" | "probability", # logits: (1, C, h, w), robot where argmax over C == class_index;
      "class_index": 1,                   #   (logits only)
      "threshold": 0.5                    # probability: (1, 1, h, w) in [0, 1], robot where > threshold
    }

plus optional free-form keys ``name``, ``description``, ``classes``, ``training``. The network has one float32
input of rank 4 ``(1, 3, H, W)`` and its first output is read; the output ``(h, w)`` may differ from the input's:
it is resized (bilinear, on the logits or probabilities) back to the image size before the decision; then only
the largest connected component is kept (``OnnxSegmenterConfig.largest_component``, on by default).
Execution providers: ``CUDAExecutionProvider`` when onnxruntime has it (``device="auto"``), else the CPU.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.checks import check_choice
from pipeline.errors import AssetError, ConfigError
from pipeline.segment.base import check_bgr_image, check_frame_index, largest_component

logger = logging.getLogger(__name__)

#: Folder of the named models (``models/segmenters/<name>/model.onnx`` + ``meta.json``).
SEGMENTER_MODELS_DIR = Path(__file__).resolve().parents[2] / "models" / "segmenters"
#: The shipped model: a small DeepLab-style network for the soft arm and the example manipulator.
DEFAULT_ONNX_MODEL = "robot_deeplab"
DEVICE_CHOICES = ("auto", "cpu", "cuda")
OUTPUT_CHOICES = ("logits", "probability")
CHANNEL_ORDER_CHOICES = ("rgb", "bgr")

_META_REQUIRED = ("input_size", "channel_order", "scale", "mean", "std", "output")
_META_OPTIONAL = ("class_index", "threshold", "size_multiple", "max_side", "name", "description", "classes",
                  "training")


@dataclass(frozen=True, kw_only=True)
class OnnxSegmenterConfig:
    """Settings of :class:`OnnxSegmenter`.

    Attributes:
        model: a model name (folder under ``models/segmenters/``), a model folder, or the path of its
            ``model.onnx`` (``meta.json`` lies beside it).
        device: ``"auto"`` (CUDA when onnxruntime offers it, else CPU), ``"cpu"`` or ``"cuda"`` (an error if
            onnxruntime has no CUDA provider).
        num_threads: onnxruntime intra-op threads; 0 lets onnxruntime choose (one per core).
        largest_component: keep only the largest 8-connected component of the network's mask (drops stray
            detections away from the robot, which is one piece in view).
        max_side: models of dynamic input size: an image whose longer side is above this is shrunk (area
            interpolation) to it before the network, and the network's scores are resized back (bilinear) to the
            image before the decision. ``None``: the model's ``meta.json`` ``max_side`` (none if it has none);
            0: never shrink. A network sees objects at the scale it was trained at: the shipped one, trained on
            640x480 renders, leaves much of a manipulator out at 2048x1536 when fed the image as it is.
    """

    model: str = DEFAULT_ONNX_MODEL
    device: str = "auto"
    num_threads: int = 0
    largest_component: bool = True
    max_side: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.model, Path):
            object.__setattr__(self, "model", str(self.model))
        if not isinstance(self.model, str) or not self.model:
            raise ConfigError(f"model: expected a model name or path, got {self.model!r}")
        check_choice(self.device, DEVICE_CHOICES, "device")
        if isinstance(self.num_threads, bool) or not isinstance(self.num_threads, int) or self.num_threads < 0:
            raise ConfigError(f"num_threads: expected an int >= 0 (0: onnxruntime's choice), got {self.num_threads!r}")
        if self.max_side is not None and (isinstance(self.max_side, bool) or not isinstance(self.max_side, int)
                                          or self.max_side < 0):
            raise ConfigError(f"max_side: expected an int >= 0 (0: never shrink) or None (the model's meta.json), "
                              f"got {self.max_side!r}")
        if not isinstance(self.largest_component, bool):
            raise ConfigError(f"largest_component: expected a bool, got {self.largest_component!r}")


@dataclass(frozen=True, kw_only=True)
class OnnxModelMeta:
    """The contents of a model's ``meta.json`` (see the module docstring for each key).

    Attributes:
        input_size: ``(H, W)`` the network takes, or ``"dynamic"`` (the image's own size).
        size_multiple: dynamic models only: the input is padded (edge pixels repeated) to a multiple of this.
        max_side: dynamic models only: an image of a longer side is shrunk to it first (0: never).
        channel_order: ``"rgb"`` or ``"bgr"``.
        scale, mean, std: normalisation ``x = (pixel * scale - mean) / std``, mean and std in the network's order.
        output: ``"logits"`` ``(1, C, h, w)`` or ``"probability"`` ``(1, 1, h, w)``.
        class_index: logits only: the robot's class.
        threshold: probability only: robot where the probability is above it.
    """

    input_size: tuple[int, int] | str
    channel_order: str
    scale: float
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    output: str
    class_index: int = 1
    threshold: float = 0.5
    size_multiple: int = 1
    max_side: int = 0


def onnx_meta_from_dict(data: object, source: str = "meta.json") -> OnnxModelMeta:
    """Validate the dict of a ``meta.json`` and build :class:`OnnxModelMeta`; ``source`` names it in errors.

    Raises:
        ConfigError: a missing or unknown key, or a value of the wrong type or range (the message names the key
            and what was expected).
    """
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: expected a JSON object, got {type(data).__name__}")
    missing = [k for k in _META_REQUIRED if k not in data]
    if missing:
        names = ", ".join(map(repr, missing))
        raise ConfigError(f"{source}: missing key(s) {names}; required: {', '.join(_META_REQUIRED)}")
    unknown = sorted(set(data) - set(_META_REQUIRED) - set(_META_OPTIONAL))
    if unknown:
        valid = ", ".join(_META_REQUIRED + _META_OPTIONAL)
        raise ConfigError(f"{source}: unknown key(s) {', '.join(map(repr, unknown))}; valid keys: {valid}")

    size = data["input_size"]
    if size == "dynamic":
        input_size: tuple[int, int] | str = "dynamic"
    elif isinstance(size, list) and len(size) == 2 and all(_is_int(s) and s > 0 for s in size):
        input_size = (int(size[0]), int(size[1]))
    else:
        raise ConfigError(f'{source}: input_size: expected [H, W] (positive ints) or "dynamic", got {size!r}')
    channel_order = data["channel_order"]
    if channel_order not in CHANNEL_ORDER_CHOICES:
        raise ConfigError(f"{source}: channel_order: expected 'rgb' or 'bgr', got {channel_order!r}")
    scale = _number(data["scale"], f"{source}: scale", positive=True)
    mean = _triple(data["mean"], f"{source}: mean", positive=False)
    std = _triple(data["std"], f"{source}: std", positive=True)
    output = data["output"]
    if output not in OUTPUT_CHOICES:
        raise ConfigError(f"{source}: output: expected one of 'logits', 'probability', got {output!r}")
    fields: dict = {}
    if output == "logits":
        if "class_index" not in data:
            raise ConfigError(f"{source}: output 'logits' needs class_index (the robot's channel)")
        if not _is_int(data["class_index"]) or data["class_index"] < 0:
            raise ConfigError(f"{source}: class_index: expected an int >= 0, got {data['class_index']!r}")
        fields["class_index"] = int(data["class_index"])
    else:
        if "threshold" not in data:
            raise ConfigError(f"{source}: output 'probability' needs threshold (e.g. 0.5)")
        threshold = _number(data["threshold"], f"{source}: threshold", positive=False)
        if not 0.0 <= threshold < 1.0:
            raise ConfigError(f"{source}: threshold: expected a number in [0, 1), got {data['threshold']!r}")
        fields["threshold"] = threshold
    if "size_multiple" in data:
        multiple = data["size_multiple"]
        if not _is_int(multiple) or multiple < 1:
            raise ConfigError(f"{source}: size_multiple: expected an int >= 1, got {multiple!r}")
        fields["size_multiple"] = int(multiple)
    if "max_side" in data:
        side = data["max_side"]
        if not _is_int(side) or side < 0:
            raise ConfigError(f"{source}: max_side: expected an int >= 0 (0: never shrink), got {side!r}")
        fields["max_side"] = int(side)
    return OnnxModelMeta(
        input_size=input_size, channel_order=channel_order, scale=scale, mean=mean, std=std, output=output, **fields
    )


def resolve_onnx_model(model: str | Path) -> tuple[Path, Path]:
    """The ``(model.onnx, meta.json)`` paths a model name, folder or ``.onnx`` path refers to.

    Raises:
        AssetError: the model file or its ``meta.json`` does not exist (the message lists the named models).
    """
    path = Path(model)
    if path.suffix == ".onnx":
        onnx_path = path
    elif path.is_dir():
        onnx_path = path / "model.onnx"
    elif len(path.parts) == 1:
        onnx_path = SEGMENTER_MODELS_DIR / str(model) / "model.onnx"
    else:
        onnx_path = path / "model.onnx"
    if not onnx_path.is_file():
        raise AssetError(
            f"ONNX model file not found: {onnx_path} (for model {str(model)!r}; named models: {_named_models()})"
        )
    meta_path = onnx_path.with_name("meta.json")
    if not meta_path.is_file():
        raise AssetError(f"meta.json not found beside the ONNX model: {meta_path}")
    return onnx_path, meta_path


def load_onnx_meta(path: str | Path) -> OnnxModelMeta:
    """Read and validate a ``meta.json``; ``AssetError`` if unreadable, ``ConfigError`` if malformed."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise AssetError(f"cannot read {path}: {e}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: not valid JSON ({e})") from None
    return onnx_meta_from_dict(data, str(path))


class OnnxSegmenter:
    """Runs an ONNX segmentation network (see the module docstring for the model contract).

    The onnxruntime session is created once, here; pickling keeps only the config (the session is rebuilt).

    Attributes:
        config: the :class:`OnnxSegmenterConfig`.
        model_path: the ``model.onnx`` file.
        meta: the model's :class:`OnnxModelMeta`.
        providers: the execution providers the session uses.
    """

    def __init__(self, config: OnnxSegmenterConfig) -> None:
        if not isinstance(config, OnnxSegmenterConfig):
            raise ConfigError(f"config: expected an OnnxSegmenterConfig, got {type(config).__name__}")
        import onnxruntime

        self.config = config
        self.model_path, meta_path = resolve_onnx_model(config.model)
        self.meta = load_onnx_meta(meta_path)
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = config.num_threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3  # errors only
        providers = _providers(config.device, onnxruntime.get_available_providers())
        try:
            self._session = onnxruntime.InferenceSession(str(self.model_path), options, providers=providers)
        except Exception as e:  # onnxruntime raises its own exception types for unreadable or invalid models
            message = " ".join(str(e).split())
            raise AssetError(f"cannot load ONNX model {self.model_path}: {message}") from None
        self.providers = tuple(self._session.get_providers())
        self._input_name = self._check_input()
        self._output_name = self._check_output()
        logger.info("ONNX segmenter %s on %s", self.model_path, ", ".join(self.providers))

    def __call__(self, image: np.ndarray, *, frame_index: int = 0) -> np.ndarray:
        """``(H, W, 3)`` uint8 BGR -> ``(H, W)`` bool; ``frame_index`` is ignored.

        Raises:
            ConfigError: the network's output has an unexpected shape.
        """
        H, W = check_bgr_image(image)
        check_frame_index(frame_index)
        meta = self.meta
        h, w = H, W  # the image as the network sees it, before any padding (shrunk to max_side)
        if meta.input_size == "dynamic":
            side = meta.max_side if self.config.max_side is None else self.config.max_side
            if 0 < side < max(H, W):  # shrunk to the scale the network knows
                h, w = max(1, round(H * side / max(H, W))), max(1, round(W * side / max(H, W)))
                image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
            m = meta.size_multiple
            Hp, Wp = -(-h // m) * m, -(-w // m) * m  # padded to a multiple of m
            net_image = cv2.copyMakeBorder(image, 0, Hp - h, 0, Wp - w, cv2.BORDER_REPLICATE)
        else:  # stretched to the network's input; its scores come back at the image's size
            Hp, Wp = H, W
            net_h, net_w = meta.input_size
            shrink = net_h < H or net_w < W
            net_image = cv2.resize(image, (net_w, net_h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        x = net_image[..., ::-1] if meta.channel_order == "rgb" else net_image  # (h, w, 3)
        x = (x.astype(np.float32) * np.float32(meta.scale) - np.float32(meta.mean)) / np.float32(meta.std)
        x = np.ascontiguousarray(x.transpose(2, 0, 1)[None])  # (1, 3, h, w)
        out = self._session.run([self._output_name], {self._input_name: x})[0]
        scores = self._check_output_array(out)[0].transpose(1, 2, 0)  # (h, w, C)
        if scores.shape[:2] != (Hp, Wp):
            scores = cv2.resize(scores, (Wp, Hp), interpolation=cv2.INTER_LINEAR).reshape(Hp, Wp, -1)
        scores = scores[:h, :w]  # the padding cut off
        if (h, w) != (H, W):  # from the shrunk image's
            scores = cv2.resize(scores, (W, H), interpolation=cv2.INTER_LINEAR).reshape(H, W, -1)
        if meta.output == "probability":
            mask = scores[..., 0] > meta.threshold
        else:
            mask = np.argmax(scores, axis=-1) == meta.class_index
        return largest_component(mask) if self.config.largest_component else mask

    def __reduce__(self) -> tuple:
        return (OnnxSegmenter, (self.config,))

    def __repr__(self) -> str:
        return f"OnnxSegmenter({self.config!r}, providers={self.providers!r})"

    def _check_input(self) -> str:
        inputs = self._session.get_inputs()
        where = f"ONNX model {self.model_path}"
        if len(inputs) != 1:
            names = ", ".join(i.name for i in inputs)
            raise ConfigError(f"{where}: expected one input (1, 3, H, W), got {len(inputs)}: {names}")
        inp = inputs[0]
        shape = list(inp.shape)
        if inp.type != "tensor(float)":
            raise ConfigError(f"{where}: expected a float32 input (1, 3, H, W), got {inp.type} {shape}")
        if len(shape) != 4:
            raise ConfigError(f"{where}: wrong input rank {len(shape)}: expected (1, 3, H, W), got {shape}")
        if _static(shape[0]) not in (None, 1) or _static(shape[1]) not in (None, 3):
            raise ConfigError(f"{where}: expected input shape (1, 3, H, W), got {shape}")
        static_hw = (_static(shape[2]), _static(shape[3]))
        if self.meta.input_size == "dynamic":
            if None not in static_hw:
                raise ConfigError(
                    f'{where}: meta.json says input_size "dynamic" but the model takes a fixed {shape[2:]} input; '
                    f"write input_size [{static_hw[0]}, {static_hw[1]}]"
                )
        else:
            for got, want, axis in zip(static_hw, self.meta.input_size, ("H", "W")):
                if got is not None and got != want:
                    raise ConfigError(
                        f"{where}: meta.json input_size {list(self.meta.input_size)} does not match the model "
                        f"input {shape} ({axis})"
                    )
        return inp.name

    def _check_output(self) -> str:
        out = self._session.get_outputs()[0]
        shape = list(out.shape)
        if len(shape) != 4:
            raise ConfigError(
                f"ONNX model {self.model_path}: unexpected output shape {shape} (rank {len(shape)}): expected "
                f"{self._expected_output()}"
            )
        channels = _static(shape[1])
        if channels is not None:
            self._check_channels(channels, shape)
        return out.name

    def _check_output_array(self, out: np.ndarray) -> np.ndarray:
        if out.ndim != 4 or out.shape[0] != 1 or min(out.shape) < 1:
            raise ConfigError(
                f"ONNX model {self.model_path}: unexpected output shape {list(out.shape)}: expected "
                f"{self._expected_output()}"
            )
        self._check_channels(out.shape[1], list(out.shape))
        return out.astype(np.float32, copy=False)

    def _check_channels(self, channels: int, shape: list) -> None:
        meta = self.meta
        if meta.output == "probability" and channels != 1:
            raise ConfigError(
                f"ONNX model {self.model_path}: unexpected output shape {shape}: meta.json says 'probability', "
                f"which needs {self._expected_output()}"
            )
        if meta.output == "logits" and channels <= meta.class_index:
            raise ConfigError(
                f"ONNX model {self.model_path}: unexpected output shape {shape}: class_index {meta.class_index} "
                f"needs at least {meta.class_index + 1} channels, {self._expected_output()}"
            )

    def _expected_output(self) -> str:
        return "(1, 1, h, w) probabilities" if self.meta.output == "probability" else "(1, C, h, w) logits"


def _providers(device: str, available: list[str]) -> list[str]:
    has_cuda = "CUDAExecutionProvider" in available
    if device == "cuda" and not has_cuda:
        raise ConfigError(
            f"device 'cuda': onnxruntime has no CUDAExecutionProvider (available: {', '.join(available)}); "
            "install onnxruntime-gpu or use device 'auto' or 'cpu'"
        )
    if device != "cpu" and has_cuda:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


def _named_models() -> str:
    names = sorted(p.parent.name for p in SEGMENTER_MODELS_DIR.glob("*/model.onnx"))
    return ", ".join(names) if names else "none"


def _static(dim: object) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: object, name: str, *, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value != value or abs(value) == float("inf"):
        raise ConfigError(f"{name}: expected a finite number, got {value!r}")
    if positive and value <= 0:
        raise ConfigError(f"{name}: expected a number > 0, got {value!r}")
    return float(value)


def _triple(value: object, name: str, *, positive: bool) -> tuple[float, float, float]:
    if not isinstance(value, list) or len(value) != 3:
        raise ConfigError(f"{name}: expected a list of 3 numbers (one per channel), got {value!r}")
    a, b, c = (_number(v, name, positive=positive) for v in value)
    return (a, b, c)
