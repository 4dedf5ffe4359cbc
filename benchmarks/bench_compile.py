"""What ``torch.compile`` would buy the soft-arm fit's steps: eager against compiled, per step, in the same run.

A warm-started tracking frame (``docs/tracking.md``) is 100 pre-fit steps and 30 rendered steps of about 3 and 4.5
ms each, nearly all of it the overhead of some 3,000 small tensor operations per step (no single one dominates).
This script builds the fit problem of one frame (the moving arm of ``bench_track.py``, seed 1, frame 0, 640x360,
order 2, state at the true control points), then times the forward and backward pass of the pre-fit loss
(``_FitProblem.skeleton_loss``, pure torch) and of the rendered loss (``_FitProblem.loss``, whose rasterizer is a
custom autograd function on numba kernels, so the compiler has to break the graph there), eager and compiled
(``torch.compile(dynamic=False)``, inductor's C++ backend: it needs a C++ compiler), and prints the compile time,
the milliseconds per step, the ratio, and the relative difference of the losses.

Static shapes are the best case for one problem. The package's option (``ShapeFitConfig.compile``, ``track shape
--compile``) compiles functions of (problem, parameters) once per process with torch's automatic dynamic shapes
instead: with static shapes a fit recompiles on every frame, whose working image's size changes with the crop
(measured: 16 s for the pre-fit loss and 5-10 s for the rendered loss on each of six frames); docs/tracking.md.

    OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 python benchmarks/bench_compile.py [--steps 200]
"""

from __future__ import annotations

import argparse
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=int, default=200, help="timed steps per variant")
    args = parser.parse_args()

    import numpy as np
    import torch

    from pipeline.camera import Camera
    from pipeline.robots import ContinuumRobot
    from pipeline.shape_estimation import ShapeFitConfig, _FitProblem, control_points_to_state, observe_mask
    from pipeline.shapes.polyline import bezier_centerline
    from pipeline.synth.soft_arm import moving_bezier_arm, render_tube_image

    W, H = 640, 360
    f = 700.0 * W / 1280.0
    K = np.array([[f, 0.0, (W - 1) / 2], [0.0, f, (H - 1) / 2], [0.0, 0.0, 1.0]])
    camera = Camera(K=K.tolist(), width=W, height=H)
    control = moving_bezier_arm(np.random.default_rng(1), K, (H, W), 1, order=2)[0]
    mask = render_tube_image(bezier_centerline(control, 201), np.linspace(0.014, 0.006, 201), K, (H, W),
                             np.random.default_rng(0))[1]
    robot = ContinuumRobot(length_m=0.2, base_radius_m=0.014, tip_radius_m=0.006)
    config = ShapeFitConfig(model="bezier", order=2)
    observation = observe_mask(mask, camera, max_side=config.working_max_side, keypoints=config.keypoint_count,
                               taper_ratio=robot.base_radius_m / robot.tip_radius_m)
    problem = _FitProblem(observation, robot, config, torch.float32)
    state = control_points_to_state(torch.from_numpy(control)[None]).float().requires_grad_(True)
    offsets = torch.zeros(1, robot.n_rings, requires_grad=True)
    params = {"control": state, "radius_offsets": offsets}

    def timed(loss_fn, steps: int) -> tuple[float, float]:
        """(ms per forward + backward, the loss) over ``steps`` after 5 untimed ones."""
        for _ in range(5):
            loss_fn(params, 0).sum().backward()
        start = time.perf_counter()
        for _ in range(steps):
            loss = loss_fn(params, 0)
            loss.sum().backward()
        return 1000.0 * (time.perf_counter() - start) / steps, float(loss.detach()[0])

    print(f"torch {torch.__version__}, threads {torch.get_num_threads()}; {args.steps} steps per variant")
    for name, loss_fn in (("pre-fit loss (skeleton_loss)", problem.skeleton_loss), ("rendered loss", problem.loss)):
        eager_ms, eager_loss = timed(loss_fn, args.steps)
        start = time.perf_counter()
        try:
            compiled = torch.compile(loss_fn, dynamic=False)
            compiled(params, 0).sum().backward()
        except Exception as error:  # no C++ compiler, an unsupported operation: say so, time the rest
            print(f"{name}: eager {eager_ms:.2f} ms per step; compile failed: {type(error).__name__}: "
                  f"{str(error).splitlines()[0][:200]}")
            continue
        compile_s = time.perf_counter() - start
        compiled_ms, compiled_loss = timed(compiled, args.steps)
        print(f"{name}: eager {eager_ms:.2f} ms per step, compiled {compiled_ms:.2f} ms "
              f"({eager_ms / compiled_ms:.1f}x; compile {compile_s:.1f} s); loss relative difference "
              f"{abs(compiled_loss - eager_loss) / abs(eager_loss):.1e}")


if __name__ == "__main__":
    main()
