"""Train the shipped robot segmenter (``robot_deeplab``) on domain-randomised synthetic renders; export to ONNX.

Run from the repository root (CPU, one torch thread)::

    python models/segmenters/train.py --out models/segmenters/robot_deeplab

The shipped model is two runs of this script. First its defaults (24 000 steps of 8 crops of 192x256) with
``--threads 2``: 73 minutes on a free 2-core machine, held-out mean IoU 0.89 (soft arm) and 0.85 (manipulator),
the loss still falling (5 000 steps had given 0.77 / 0.75, 12 000 steps 0.85 / 0.82). Then a fine-tune of that
model on 1 500 fresh renders, batch norms frozen (``--init``: the ``model.pt`` an export saves beside
``model.onnx``; the shipped model has none, so its weights are read back from the ONNX file, where the export
folded the batch norms into the convolutions)::

    python models/segmenters/train.py --init models/segmenters/robot_deeplab --pool-offset 1500 --lr 2e-3

(one thread, 101 minutes beside another job): held-out mean IoU **0.92 (soft arm) and 0.91 (manipulator)**
(medians 0.97 / 0.93). ``train_log.json`` keeps the fine-tune's log with the first run's as ``init_log``.

The network is DeepLabv3+-style and small (184 k parameters, 0.75 MB): a 4x4 stride-4 patch stem, plain 3x3
convolution blocks at strides 4 and 8 (the last ones dilated instead of strided: output stride 8; on one CPU
thread plain convolutions learnt faster per second than depthwise-separable ones), an ASPP head (1x1, three
dilated depthwise-separable 3x3 branches at rates 3, 6, 9, image pooling) and a decoder that joins the stride-4
features, with the 2-class logits upsampled (bilinear) to the input size.

The data are drawn at random, seeded by ``--seed``:

- soft arm: random Bezier (quadratic, cubic) and piecewise-constant-curvature centrelines of random length and
  radii, as a tube drawn by ``pipeline.synth.render_tube_image`` (its clutter) or by
  ``pipeline.synth.manipulator.render_mesh_image`` (random lighting, its clutter);
- manipulator: ``models/robots/toy_arm`` at random joint angles seen by a random camera
  (``pipeline.synth.manipulator.random_manipulator_image``);
- 8% empty clutter;

every one in random colours (the arm colours include, but are not limited to, the demo's pink-red), then random
scale and crop, flips, colour cast, contrast, gamma, blur, noise and JPEG. A pool of renders is drawn once and
re-cropped each step. The model is exported with dynamic height and width (opset 17), so the segmenter feeds each
image at its own size (padded to a multiple of 8); ``meta.json`` says so. ``train_log.json`` keeps the settings,
the loss curve and the held-out IoU of the exported model on fresh 640x480 images of each robot.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
# numba's OpenMP pool (the hard rasterizer) shares libgomp with torch: at its default (one thread per core) it
# resets torch's thread count and oversubscribes the cores, which made training steps 10-100 times slower.
os.environ.setdefault("NUMBA_NUM_THREADS", "1")

from pipeline.evaluate import mask_iou  # noqa: E402
from pipeline.robots.manipulator import load_urdf_robot  # noqa: E402
from pipeline.shapes.polyline import bezier_centerline  # noqa: E402
from pipeline.errors import ConfigError  # noqa: E402
from pipeline.synth.soft_arm import pcc_arm, random_bezier_arm, render_tube_image, tube_mesh  # noqa: E402
from pipeline.synth.manipulator import (  # noqa: E402
    random_background,
    random_colors,
    random_intrinsics,
    random_lighting,
    random_manipulator_image,
    randomize_photometric,
    render_mesh_image,
)

TOY_ARM_URDF = REPO / "models" / "robots" / "toy_arm" / "toy_arm.urdf"
KINDS = ("soft_arm", "manipulator", "empty")
#: Held-out images are drawn from seeds at and above this offset (training pools use seeds below it).
HELD_OUT_SEED_OFFSET = 1_000_000
MEAN_RGB = (0.485, 0.456, 0.406)
STD_RGB = (0.229, 0.224, 0.225)
SIZE_MULTIPLE = 8
#: The torch weights saved beside ``model.onnx`` at export.
STATE_DICT = "model.pt"


# ----------------------------------------------------------------------------------------------------------- model
class ConvBNReLU(nn.Sequential):
    def __init__(self, cin: int, cout: int, k: int = 3, stride: int = 1, dilation: int = 1, groups: int = 1):
        pad = dilation * (k - 1) // 2 if stride == 1 or k % 2 else 0
        super().__init__(
            nn.Conv2d(cin, cout, k, stride, pad, dilation, groups, bias=False), nn.BatchNorm2d(cout), nn.ReLU(True)
        )


class SeparableConv(nn.Sequential):
    """Depthwise 3x3 (stride, dilation) then pointwise 1x1, each with batch norm and ReLU."""

    def __init__(self, cin: int, cout: int, stride: int = 1, dilation: int = 1):
        super().__init__(ConvBNReLU(cin, cin, 3, stride, dilation, groups=cin), ConvBNReLU(cin, cout, 1))


class ASPP(nn.Module):
    """Atrous spatial pyramid pooling: 1x1, dilated separable 3x3 branches and image pooling, fused by a 1x1."""

    def __init__(self, cin: int, cout: int, rates: tuple[int, ...]):
        super().__init__()
        self.branches = nn.ModuleList([ConvBNReLU(cin, cout, 1)] + [SeparableConv(cin, cout, 1, r) for r in rates])
        self.pool = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(cin, cout, 1), nn.ReLU(True))
        self.project = ConvBNReLU(cout * (len(rates) + 2), cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = self.pool(x).expand(-1, -1, x.shape[2], x.shape[3])  # (B, C, h, w)
        return self.project(torch.cat([b(x) for b in self.branches] + [pooled], dim=1))


class RobotDeepLab(nn.Module):
    """``(B, 3, H, W)`` normalised RGB -> ``(B, 2, H, W)`` logits (background, robot).

    A 4x4 stride-4 patch stem, 3x3 convolution blocks at strides 4 and 8 (the last ones dilated instead of
    strided: output stride 8), ASPP, and a decoder at stride 4 that joins the stride-4 features (DeepLabv3+).
    Plain 3x3 convolutions in the backbone: on one CPU thread they train faster per parameter than depthwise ones.
    """

    def __init__(self, width: int = 48):
        super().__init__()
        self.stem = ConvBNReLU(3, 24, k=4, stride=4)  # /4 (patches)
        self.low = ConvBNReLU(24, 32)  # /4: low-level features for the decoder
        self.mid = nn.Sequential(ConvBNReLU(32, 48, stride=2), ConvBNReLU(48, 64))  # /8
        self.deep = nn.Sequential(ConvBNReLU(64, 64, dilation=2), ConvBNReLU(64, 64, dilation=4))  # /8, dilated
        self.aspp = ASPP(64, width, rates=(3, 6, 9))
        self.low_project = ConvBNReLU(32, 24, 1)
        self.decoder = nn.Sequential(ConvBNReLU(width + 24, 32), ConvBNReLU(32, 32))
        self.classifier = nn.Conv2d(32, 2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        low = self.low(self.stem(x))  # (B, 32, H/4, W/4)
        deep = self.aspp(self.deep(self.mid(low)))  # (B, width, H/8, W/8)
        up = F.interpolate(deep, size=low.shape[2:], mode="bilinear", align_corners=False)
        logits = self.classifier(self.decoder(torch.cat([up, self.low_project(low)], dim=1)))  # (B, 2, H/4, W/4)
        return F.interpolate(logits, size=x.shape[2:], mode="bilinear", align_corners=False)


# ------------------------------------------------------------------------------------------------------------ data
class SampleMaker:
    """Draws ``(image (H, W, 3) uint8 BGR, mask (H, W) bool)`` of a robot kind; holds the loaded toy arm."""

    def __init__(self) -> None:
        self.toy_arm = load_urdf_robot(TOY_ARM_URDF, "base_link")

    def __call__(self, kind: str, rng: np.random.Generator, image_size: tuple[int, int], photometric: bool):
        if kind == "manipulator":
            sample = random_manipulator_image(self.toy_arm, rng, image_size, photometric=False)
            image, mask = sample.image, sample.mask
        elif kind == "soft_arm":
            image, mask = soft_arm_image(rng, image_size)
        elif kind == "empty":
            image, mask = random_background(rng, image_size), np.zeros(image_size, bool)
        else:
            raise ConfigError(f"kind: expected one of {', '.join(KINDS)}, got {kind!r}")
        return (randomize_photometric(image, rng) if photometric else image), mask


def soft_arm_image(rng: np.random.Generator, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """A random soft arm (Bezier or PCC centreline, random size and colour) drawn by one of the two renderers."""
    H, W = image_size
    K = random_intrinsics(rng, image_size)
    while True:
        length = rng.uniform(0.12, 0.3)
        distance = K[0, 0] * length / (rng.uniform(0.3, 0.8) * W)  # the arm spans 30-80% of the width
        model = rng.choice(["quadratic", "cubic", "pcc"])
        try:
            if model == "pcc":
                centerline = pcc_arm(rng, K, image_size, length_m=length, distance_m=distance,
                                     n_segments=int(rng.integers(1, 4)), base_nearer_border=False)  # fmt: skip
            else:
                order = 2 if model == "quadratic" else 3
                control = random_bezier_arm(rng, K, image_size, length_m=length, distance_m=distance, order=order,
                                            max_bend_rad=rng.uniform(0.5, 3.0), base_nearer_border=False)  # fmt: skip
                centerline = bezier_centerline(control, 101)
            break
        except ConfigError:
            continue
    base = length * rng.uniform(0.04, 0.1)
    radii = np.linspace(base, base * rng.uniform(0.3, 0.9), len(centerline))
    if rng.uniform() < 0.5:
        color = random_colors(rng, 1)[0]
        hsv = cv2.cvtColor(np.uint8([[color]]), cv2.COLOR_BGR2HSV)[0, 0]
        if hsv[1] < 80:  # render_tube_image keeps clutter hues away from saturated arm colours only
            hsv[1] = 180
            color = cv2.cvtColor(np.uint8([[hsv]]), cv2.COLOR_HSV2BGR)[0, 0].astype(np.float64)
        return render_tube_image(centerline, radii, K, image_size, rng, arm_color_bgr=tuple(int(c) for c in color),
                                 noise_std=rng.uniform(0.0, 4.0))  # fmt: skip
    verts, faces = (a.numpy() for a in tube_mesh(centerline, radii, n_angles=32))
    color = random_colors(rng, 1)
    background = random_background(rng, (H, W), color)
    return render_mesh_image(verts, faces, np.repeat(color, len(faces), 0), K, background, random_lighting(rng))


def draw_kind(rng: np.random.Generator) -> str:
    u = rng.uniform()
    return "empty" if u < 0.08 else ("soft_arm" if u < 0.54 else "manipulator")


def random_crop(image, mask, rng, crop_hw):
    """Random scale (0.4-1.0 of the render), random crop of ``crop_hw`` (mostly over the robot), random flip."""
    ch, cw = crop_hw
    H, W = mask.shape
    s = rng.uniform(max(0.4, ch / H, cw / W), 1.0)
    h, w = max(int(round(H * s)), ch), max(int(round(W * s)), cw)
    image = cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA)
    mask = cv2.resize(mask.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST).astype(bool)
    ys, xs = np.nonzero(mask)
    if len(ys) and rng.uniform() < 0.6:  # over a robot pixel
        k = rng.integers(len(ys))
        y0 = int(np.clip(ys[k] - rng.integers(0, ch), 0, h - ch))
        x0 = int(np.clip(xs[k] - rng.integers(0, cw), 0, w - cw))
    else:
        y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    image, mask = image[y0 : y0 + ch, x0 : x0 + cw], mask[y0 : y0 + ch, x0 : x0 + cw]
    if rng.uniform() < 0.5:
        image, mask = image[:, ::-1], mask[:, ::-1]
    return np.ascontiguousarray(image), np.ascontiguousarray(mask)


def to_tensor(images_bgr: np.ndarray) -> torch.Tensor:
    """``(B, H, W, 3)`` uint8 BGR -> ``(B, 3, H, W)`` float32 normalised RGB (the meta.json normalisation)."""
    x = torch.from_numpy(np.ascontiguousarray(images_bgr[..., ::-1])).float().div_(255.0)
    x = (x - torch.tensor(MEAN_RGB)) / torch.tensor(STD_RGB)
    return x.permute(0, 3, 1, 2).contiguous()


# ------------------------------------------------------------------------------------------------------ train/eval
def held_out_set(maker: SampleMaker, kind: str, count: int, seed: int, image_size=(480, 640)):
    """``count`` fresh images of ``kind`` (photometric changes on), seeds ``HELD_OUT_SEED_OFFSET + seed*1000 + i``."""
    out = []
    for i in range(count):
        rng = np.random.default_rng(HELD_OUT_SEED_OFFSET + seed * 1000 + i)
        out.append(maker(kind, rng, image_size, photometric=True))
    return out


def evaluate_segmenter(segmenter, samples) -> dict:
    ious = [mask_iou(segmenter(image), mask) for image, mask in samples]
    return {"mean_iou": float(np.mean(ious)), "median_iou": float(np.median(ious)), "min_iou": float(np.min(ious)),
            "count": len(ious)}  # fmt: skip


def dice_ce_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy plus soft Dice of the robot class; ``logits (B, 2, H, W)``, ``target (B, H, W)`` int64."""
    ce = F.cross_entropy(logits, target)
    p = logits.softmax(dim=1)[:, 1]  # (B, H, W)
    t = target.float()
    dice = 1.0 - (2.0 * (p * t).sum() + 1.0) / (p.sum() + t.sum() + 1.0)
    return ce + dice


def load_init(model: "RobotDeepLab", path: Path) -> None:
    """Start ``model`` from a trained model (its folder, or its ``model.onnx``): the ``model.pt`` state dict saved
    beside ``model.onnx`` at export; where there is none (the shipped model, exported before this script saved
    one), the weights read back from the ONNX file by :func:`load_onnx_weights`."""
    folder = path if path.is_dir() else path.parent
    if (folder / STATE_DICT).is_file():
        model.load_state_dict(torch.load(folder / STATE_DICT, weights_only=True))
    else:
        load_onnx_weights(model, path)


def load_onnx_weights(model: "RobotDeepLab", path: Path) -> None:
    """Start ``model`` from an exported ``model.onnx`` (a file or its folder) of the same architecture.

    Kept only for the shipped ``robot_deeplab``, which has no ``model.pt``: it depends on the exporter's node names.
    The export folds every batch norm into the convolution before it, so each such batch norm becomes the identity
    (statistics 0 / 1, scale 1) and carries the folded bias; train it afterwards with :func:`freeze_batch_norm`.
    Convolutions are found by their module path in the ONNX node names (:func:`onnx_module_path`).
    """
    import onnx
    from onnx import numpy_helper

    path = path / "model.onnx" if path.is_dir() else path
    graph = onnx.load(str(path)).graph
    weights = {i.name: torch.from_numpy(numpy_helper.to_array(i).copy()) for i in graph.initializer}
    modules = dict(model.named_modules())
    loaded = set()
    with torch.no_grad():
        for node in (n for n in graph.node if n.op_type == "Conv"):
            name = onnx_module_path(node.name)
            conv = modules.get(name)
            if not isinstance(conv, nn.Conv2d) or conv.weight.shape != weights[node.input[1]].shape:
                raise ConfigError(f"{path}: convolution {node.name!r} does not match this architecture")
            conv.weight.copy_(weights[node.input[1]])
            bias = weights[node.input[2]] if len(node.input) > 2 else torch.zeros(conv.out_channels)
            if conv.bias is not None:
                conv.bias.copy_(bias)
            else:  # a folded batch norm: the next module of the ConvBNReLU
                parent, index = name.rsplit(".", 1)
                bn = modules[f"{parent}.{int(index) + 1}"]
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
                bn.weight.fill_(1.0)
                bn.bias.copy_(bias)
            loaded.add(name)
    missing = [n for n, m in modules.items() if isinstance(m, nn.Conv2d) and n not in loaded]
    if missing:
        raise ConfigError(f"{path}: no weights for {', '.join(missing)}")


def onnx_module_path(node_name: str) -> str:
    """``/aspp/branches.1/branches.1.0/branches.1.0.0/Conv`` -> ``aspp.branches.1.0.0`` (torch's export names:
    one part per module, each nested ``Sequential`` repeating its parent's name)."""
    parts: list[str] = []
    for part in node_name.strip("/").split("/")[:-1]:
        if parts and part.startswith(parts[-1] + "."):
            parts[-1] = part  # a child of the previous part, named with its full local path
        else:
            parts.append(part)
    return ".".join(parts)


def freeze_batch_norm(model: nn.Module) -> None:
    """Batch norms in eval mode (fixed statistics, trainable scale and bias): for fine-tuning a loaded model."""
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()


def export_onnx(model: nn.Module, path: Path) -> None:
    """Write ``model.onnx`` (dynamic height and width) to ``path`` and its torch ``state_dict()`` beside it
    (``model.pt``, the start of a later fine-tune)."""
    model = model.to(memory_format=torch.contiguous_format).eval()
    dummy = torch.zeros(1, 3, 240, 320)
    torch.onnx.export(
        model, (dummy,), str(path), input_names=["image"], output_names=["logits"], opset_version=17,
        dynamic_axes={"image": {2: "height", 3: "width"}, "logits": {2: "height", 3: "width"}}, dynamo=False,
    )  # fmt: skip
    torch.save(model.state_dict(), path.parent / STATE_DICT)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "models" / "segmenters" / "robot_deeplab")
    parser.add_argument("--steps", type=int, default=24000)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--crop", default="192x256", help="training crop HxW")
    parser.add_argument("--render", default="480x640", help="size HxW of the pool renders")
    parser.add_argument("--pool", type=int, default=1500, help="renders drawn before training")
    parser.add_argument("--lr", type=float, default=5e-3)
    parser.add_argument("--width", type=int, default=48, help="ASPP / decoder channels")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--held-out", type=int, default=60, help="held-out 640x480 images per robot")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (other jobs share the cores)")
    parser.add_argument("--init", type=Path, help="fine-tune: start from this trained model's folder (or its "
                        "model.onnx): its model.pt, or for the shipped model its ONNX weights")
    parser.add_argument("--pool-offset", type=int, default=0,
                        help="draw the pool from seeds [seed, offset + i] (fresh renders for a fine-tune)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    torch.manual_seed(args.seed)
    crop = tuple(int(v) for v in args.crop.split("x"))
    render = tuple(int(v) for v in args.render.split("x"))
    started, cpu_started = time.perf_counter(), time.process_time()
    maker = SampleMaker()

    pool_images = np.empty((args.pool, *render, 3), np.uint8)
    pool_masks = np.empty((args.pool, *render), bool)
    pool_kinds = []
    for i in range(args.pool):
        rng = np.random.default_rng([args.seed, args.pool_offset + i])
        kind = draw_kind(rng)
        pool_images[i], pool_masks[i] = maker(kind, rng, render, photometric=False)
        pool_kinds.append(kind)
    print(f"pool of {args.pool} renders in {time.perf_counter() - started:.0f} s", flush=True)

    torch.set_num_threads(args.threads)  # again: drawing the pool ran numba's OpenMP pool
    model = RobotDeepLab(args.width)
    init_log = None  # the log of the model fine-tuned from, kept in this one's log
    if args.init is not None:
        load_init(model, args.init)
        previous = (args.init if args.init.is_dir() else args.init.parent) / "train_log.json"
        init_log = json.loads(previous.read_text()) if previous.is_file() else None
    model = model.to(memory_format=torch.channels_last)  # faster convolutions on CPU
    params = sum(p.numel() for p in model.parameters())
    optimizer = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, args.lr, total_steps=args.steps, pct_start=0.05)
    rng = np.random.default_rng([args.seed, 1 << 20])
    curve, smooth = [], None
    train_started = time.perf_counter()
    model.train()
    if args.init is not None:
        freeze_batch_norm(model)
    for step in range(1, args.steps + 1):
        images, masks = [], []
        for k in rng.integers(0, args.pool, args.batch):
            image, mask = random_crop(pool_images[k], pool_masks[k], rng, crop)
            images.append(randomize_photometric(image, rng))
            masks.append(mask)
        x = to_tensor(np.stack(images)).contiguous(memory_format=torch.channels_last)
        target = torch.from_numpy(np.stack(masks)).long()
        loss = dice_ce_loss(model(x), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        smooth = float(loss.detach()) if smooth is None else 0.95 * smooth + 0.05 * float(loss.detach())
        if step % 25 == 0 or step == args.steps:
            elapsed = time.perf_counter() - train_started
            cpu = time.process_time() - cpu_started
            curve.append({"step": step, "loss": round(smooth, 5), "seconds": round(elapsed, 1),
                          "cpu_seconds": round(cpu, 1)})  # fmt: skip
            if step % 250 == 0 or step == args.steps:
                print(f"step {step}/{args.steps} loss {smooth:.4f} {elapsed:.0f} s ({cpu:.0f} s CPU)", flush=True)

    args.out.mkdir(parents=True, exist_ok=True)
    export_onnx(model, args.out / "model.onnx")
    meta = {
        "name": "robot_deeplab",
        "description": "DeepLabv3+-style robot segmenter (soft arm and example manipulator), trained on synthetic "
        "domain-randomised renders by models/segmenters/train.py",
        "input_size": "dynamic",
        "size_multiple": SIZE_MULTIPLE,
        # the scale of the training renders (480x640, scaled 0.4-1.0): a manipulator at 2048x1536 fed as it is
        # comes out at mask IoU 0.36-0.61, shrunk to 960 at 0.82-0.93 (docs/segmenters.md)
        "max_side": 960,
        "channel_order": "rgb",
        "scale": 1.0 / 255.0,
        "mean": list(MEAN_RGB),
        "std": list(STD_RGB),
        "output": "logits",
        "class_index": 1,
        "classes": ["background", "robot"],
    }
    (args.out / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    train_seconds = time.perf_counter() - train_started

    from pipeline.segment import OnnxSegmenter, OnnxSegmenterConfig

    segmenter = OnnxSegmenter(OnnxSegmenterConfig(model=str(args.out), device="cpu", num_threads=args.threads))
    held_out = {kind: evaluate_segmenter(segmenter, held_out_set(maker, kind, args.held_out, args.seed))
                for kind in ("soft_arm", "manipulator")}  # fmt: skip
    for kind, result in held_out.items():
        print(f"held-out {kind}: mean IoU {result['mean_iou']:.4f} (median {result['median_iou']:.4f}, "
              f"min {result['min_iou']:.4f}, {result['count']} images 640x480)")  # fmt: skip
    log = {
        "settings": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if k != "out"},
        "parameters": params,
        "onnx_bytes": (args.out / "model.onnx").stat().st_size,
        "torch": torch.__version__,
        "train_seconds": round(train_seconds, 1),
        "total_seconds": round(time.perf_counter() - started, 1),
        "total_cpu_seconds": round(time.process_time() - cpu_started, 1),
        "load_average_at_end": os.getloadavg()[0],
        "pool_kinds": {k: pool_kinds.count(k) for k in KINDS},
        "loss_curve": curve,
        "held_out_640x480": held_out,
        "init_log": init_log,
    }
    (args.out / "train_log.json").write_text(json.dumps(log, indent=1) + "\n")
    print(f"wrote {args.out} ({log['onnx_bytes']} bytes, {params} parameters) in {log['total_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
