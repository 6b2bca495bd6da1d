"""A fit setting's cost per training step, as a ratio to the plain recipe's, in one process.

    python -m bench.speed.fit_step [--gaussians 36000] [--size 228x171] [--views 8]
                                   [--steps 20] [--rounds 3] [--out reports/bench_fit_step.csv]

Each recipe (the plain one, the monocular depth prior on the training views, the prior with
pseudo views on every second step, and its guarded form: the whole view, 8-pixel blocks,
trusted) gets a fitter on the same generated 2DGS scene: `--views`
training photographs rendered from it at `--size`, `--gaussians` random start points, the step
counter past every regulariser's start (the late part of a fit, densification aside). The
recipes then take turns, `--steps` steps each per round, for `--rounds` rounds; a recipe's
figure is the median of its rounds' ms per step. The depth prior needs `make weights`
(FastDepth). --quick: 2,000 Gaussians at 48x36, 3 steps, one round (what the tests run).
"""

from __future__ import annotations

import argparse
import statistics
import time

import pandas as pd
import torch

from bench import OUT_HELP, REPORTS, ROOT, print_and_write
from sagonline.core.machine import describe_device
from sagonline.fitting import FitConfig, SceneFitter
from sagonline.render.rasterize import rasterize
from sagonline.scene.generator import make_scene

FASTDEPTH = ROOT / "weights" / "fastdepth" / "fastdepth.onnx"
RECIPES = {
    "plain": {},
    "depth prior": {"lambda_depth": 0.05},
    "depth prior + pseudo views every 2nd step": {"lambda_depth": 0.05, "depth_pseudo_every": 2},
    "depth prior, whole view, pooled, trusted": {
        "lambda_depth": 0.05,
        "depth_patch": 0,
        "depth_pool": 8,
        "depth_trust": True,
    },
}


def fitters(args) -> dict[str, SceneFitter]:
    """One fitter per recipe, on the same photographs and start points, past every start."""
    s = make_scene(
        layout="forward",
        num_gaussians=max(args.gaussians // 4, 500),
        width=args.width,
        height=args.height,
        num_train_views=args.views,
        num_eval_views=1,
    )
    photos = [rasterize(s.gaussians, c).rgb.clamp(0, 1) for c in s.train_cameras]
    out = {}
    for name, settings in RECIPES.items():
        cfg = FitConfig(
            init_points=args.gaussians,
            background_points=0,
            holdout_every=10**6,
            depth_model=str(FASTDEPTH),
            **settings,
        )
        fitter = SceneFitter(cfg, s.train_cameras, photos)
        fitter.step = 1000  # past the regularisers' and the pseudo views' starts
        out[name] = fitter
    return out


def time_steps(fitter: SceneFitter, steps: int) -> float:
    """ms per training step over `steps` steps (the views in turn)."""
    start = time.perf_counter()
    for k in range(steps):
        fitter.train_step(fitter.train_idx[k % len(fitter.train_idx)], 0.5)
        fitter.step += 1
    return (time.perf_counter() - start) * 1000 / steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gaussians", type=int, default=36_000)
    ap.add_argument("--size", default="228x171", help="WxH of the photographs")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=str(REPORTS / "bench_fit_step.csv"), help=OUT_HELP)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.size, args.steps, args.rounds = 2_000, "48x36", 3, 1
    try:
        args.width, args.height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise SystemExit(f"error: --size {args.size!r}: WxH, say 228x171") from None
    if not FASTDEPTH.is_file():
        raise SystemExit(f"error: {FASTDEPTH} not found (run `make weights`)")
    runs = fitters(args)
    for fitter in runs.values():
        time_steps(fitter, 1)  # warm up: kernels loaded, buffers allocated
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(args.rounds):
        for name, fitter in runs.items():
            times[name].append(time_steps(fitter, args.steps))
    plain = statistics.median(times["plain"])
    machine = describe_device()
    rows = [
        {
            "recipe": name,
            "ms_per_step": round(statistics.median(t), 1),
            "ratio_to_plain": round(statistics.median(t) / plain, 3),
            "rounds": len(t),
            "steps_per_round": args.steps,
            "gaussians": args.gaussians,
            "size": args.size,
            "threads": torch.get_num_threads(),
            "device": machine["cpu"],
            "load_average_1m": machine["load_average_1m"],
        }
        for name, t in times.items()
    ]
    table = pd.DataFrame(rows)
    print_and_write(table, args.out)


if __name__ == "__main__":
    main()
