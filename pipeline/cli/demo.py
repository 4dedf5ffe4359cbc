"""``pipeline demo``: run the bundled examples end to end and print what they measured.

1. renderer: the soft arm of ``data/soft_arm/quadratic`` rendered from its true centreline, soft and hard, compared
   with the example's mask;
2. shape: that arm's 3D shape reconstructed from its RGB image (colour segmenter, preset ``soft_arm``), scored
   against its truth;
3. pose: the example manipulator's ``T_cam_root`` estimated from its RGB image (the shipped ONNX segmenter) and
   its joint readings, scored.
Needs the repository checkout (the examples live in ``data/`` and ``models/``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

DATA = Path(__file__).resolve().parents[2] / "data"


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="run the bundled examples and print their errors",
        description="Render the bundled soft-arm example, reconstruct its shape, estimate the example "
        "manipulator's pose; write pictures, results and a summary JSON to --out-dir and print the errors.",
    )
    parser.add_argument("--out-dir", default="out/demo", metavar="DIR", help="where results go (default out/demo)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import json

    from pipeline.io import write_json

    from pipeline.demo.pose import demo_pose
    from pipeline.demo.shape import demo_shape

    out_dir = Path(args.out_dir)
    summary = {"render": demo_render(out_dir / "render")}
    summary["shape"] = demo_shape(out_dir / "shape")
    summary["pose"] = demo_pose(out_dir / "pose")
    write_json(out_dir / "summary.json", summary)
    print(json.dumps(summary, indent=1))
    print(f"pictures and results in {out_dir}/")
    return 0


def demo_render(out_dir: Path) -> dict:
    """Soft and hard silhouettes of the bundled soft arm from its true shape; IoU against its mask."""
    import json
    import time

    import torch

    from pipeline.camera import load_camera
    from pipeline.evaluate import mask_iou
    from pipeline.io import read_image, read_mask, write_image, write_mask
    from pipeline.render import SoftRasterSettings, render_hard, render_silhouette
    from pipeline.robots import ContinuumRobot
    from pipeline.shapes.tube import bezier_tube_vertices
    from pipeline.viz import draw_outline, gray_to_bgr

    example = DATA / "soft_arm" / "quadratic"
    camera = load_camera(example / "camera.json")
    truth = json.loads((example / "truth.json").read_text())
    robot = ContinuumRobot(length_m=truth["length_m"], base_radius_m=truth["base_radius_m"],
                           tip_radius_m=truth["tip_radius_m"])
    control = torch.tensor(truth["control_points_cam_m"], dtype=torch.float32)[None]
    verts = bezier_tube_vertices(control, robot.initial_radii_m()[None], robot.n_angles).requires_grad_(True)
    faces, K = robot.faces(), camera.K_tensor(torch.float32)
    settings = SoftRasterSettings.from_sigma(1.0)
    render_silhouette(verts, faces, K, camera.image_size, settings).sum().backward()  # compiles on first use
    t0 = time.perf_counter()
    soft = render_silhouette(verts, faces, K, camera.image_size, settings)
    soft.sum().backward()
    seconds = time.perf_counter() - t0
    hard = render_hard(verts.detach(), faces, K, camera.image_size)[0].numpy()
    mask = read_mask(example / "mask.png", camera.image_size)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_image(out_dir / "silhouette_soft.png", gray_to_bgr(soft[0].detach().numpy()))
    write_mask(out_dir / "silhouette_hard.png", hard)
    write_image(out_dir / "overlay.png", draw_outline(read_image(example / "image.png"), hard))
    return {
        "mesh": f"{verts.shape[1]} vertices, {faces.shape[0]} faces",
        "image_size_hw": list(camera.image_size),
        "sigma_px2": settings.sigma_px2,
        "soft_forward_backward_ms": round(1e3 * seconds, 1),
        "hard_vs_bundled_mask_iou": mask_iou(hard, mask),
        "files": sorted(p.name for p in out_dir.glob("*.png")),
    }
