"""Rasterizer speed: ms/frame for render and render+trace, Gaussian-pixel evaluations/s, and
the training step (render + backward of an image loss) that scene fitting repeats.

    python bench/bench_render.py [--repeats 3] [--devices cpu,cuda] [--out reports/bench_render.csv]

Scenes: the trained donut (3DGS, 45,624 Gaussians, from ../shared/data) and a generated 360-degree
2DGS scene of 200k surfels, both at 960x540. On CUDA both backends (torch, gsplat) run when
gsplat is installed. "trace" streams every (pixel, Gaussian) pair with T > 0.01 to a consumer
that reduces it (as the vote does); "vote pass" is the trace-only pass the vote uses
(no colour, stops at T <= eps, centre within 2 px); "vote ms/mask" is one whole RGC vote of a
3-label mask as `consensus_vote` runs it (projection, tile lists, walk, histogram): the tiled
PyTorch trace reduced by the vote's accumulator (torch), or the compiled trace-and-vote kernel
(native), whose "vote speed-up" is the torch row's time over its own; "label" columns are the
label renders scoring uses (one-hot composite, most-visible ids) and the slower one's ratio to
the image render. The native kernel streams no trace, so its trace columns are empty; "step"
is forward + backward through every Gaussian parameter, the fitting loop's inner cost.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from functools import partial
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import sagonline  # noqa: E402, F401, I001 (first: sets the OpenMP wait policy before torch loads)
import pandas as pd  # noqa: E402
import torch  # noqa: E402

from sagonline.io.cameras import load_nerf_transforms  # noqa: E402
from sagonline.consensus import VoteConfig, consensus_vote  # noqa: E402
from sagonline.gaussians import Gaussians  # noqa: E402
from sagonline.io import read_scene  # noqa: E402
from sagonline.render import RasterStats, TraceRequest, render, render_labels  # noqa: E402
from sagonline.render.gsplat_backend import gsplat_available  # noqa: E402
from sagonline.render.native import native_available  # noqa: E402
from sagonline.scene_generator import make_scene  # noqa: E402
from sagonline.utils import describe_device  # noqa: E402


def scenes():
    donut_dir = ROOT.parent / "shared" / "data" / "donut_3dgs"
    if donut_dir.exists():
        cam = load_nerf_transforms(donut_dir / "transforms.json")[0].scaled(960, 540)
        yield "donut (3DGS, 45,624)", read_scene(donut_dir / "point_cloud.ply"), cam
    else:
        print(f"note: {donut_dir} not found; skipping the donut", file=sys.stderr)
    s = make_scene(layout="360", num_gaussians=200_000, width=960, height=540, num_train_views=4)
    yield f"synthetic 360 (2DGS, {len(s.gaussians):,})", s.gaussians, s.train_cameras[1]


def training_step(g: Gaussians, cam, backend: str) -> None:
    """Render with every parameter requiring grad, then backward an L1 loss to a grey image."""
    leaves = {
        k: getattr(g, k).detach().clone().requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "sh")
    }
    out = render(Gaussians(**leaves), cam, backend=backend)
    (out.rgb - 0.5).abs().mean().backward()


def one_vote(g: Gaussians, cam, backend: str) -> None:
    """One RGC vote of a fixed random 3-label mask, as the pipeline runs it."""
    gen = torch.Generator().manual_seed(0)
    mask = torch.randint(0, 3, (cam.height, cam.width), generator=gen).numpy()
    consensus_vote(g, [cam], [mask], 3, VoteConfig(), backend=backend)


def label_render(g: Gaussians, cam, backend: str, mode: str) -> None:
    """One 3-label mask render (one-hot composite or most-visible ids), as scoring runs it."""
    labels = torch.arange(len(g), device=g.device) % 3
    render_labels(g, cam, labels, 3, mode=mode, backend=backend)


def timed(fn, repeats: int, device: str) -> float:
    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    fn()  # warm-up
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--devices", default="cpu,cuda")
    ap.add_argument("--out", default=str(ROOT / "reports" / "bench_render.csv"))
    args = ap.parse_args()
    devices = [d for d in args.devices.split(",") if d == "cpu" or torch.cuda.is_available()]
    rows, rule = [], VoteConfig()
    for name, gaussians, cam in scenes():
        for device in devices:
            g, c = gaussians.to(device), cam.to(device)
            if device == "cuda":
                backends = ["torch"] + (["gsplat"] if gsplat_available() else [])
            else:
                backends = ["torch"] + (["native"] if native_available() else [])
            for backend in backends:
                stats = RasterStats()
                sink = []

                def consume(chunk, sink=sink):
                    sink.append(len(chunk))

                run = partial(render, g, c, backend=backend)
                plain = timed(run, args.repeats, device)
                step = timed(partial(training_step, g, c, backend), args.repeats, device)
                traced = vote = None
                if backend != "native":  # traces always run on the tiled PyTorch path there
                    with_image = TraceRequest(consume, rule.eps, image=True)
                    traced = timed(partial(run, trace=with_image), args.repeats, device)
                    vote_pass = TraceRequest(consume, rule.eps, max_distance=rule.delta)
                    vote = timed(partial(run, trace=vote_pass), args.repeats, device)
                vote_ms = 1000 * timed(partial(one_vote, g, c, backend), args.repeats, device)
                onehot_ms, ids_ms = (
                    1000 * timed(partial(label_render, g, c, backend, mode), args.repeats, device)
                    for mode in ("onehot", "ids")
                )
                if backend == "torch":
                    render(g, c, stats=stats)
                    torch_vote_ms = vote_ms
                rows.append(
                    {
                        "scene": name,
                        "device": device,
                        "backend": backend,
                        "render_ms": 1000 * plain,
                        "render_trace_ms": 1000 * traced if traced else None,
                        "trace_ratio": traced / plain if traced else None,
                        "vote_pass_ms": 1000 * vote if vote else None,
                        "vote_ms_per_mask": vote_ms,
                        "vote_speedup": torch_vote_ms / vote_ms if backend != "torch" else None,
                        "label_onehot_ms": onehot_ms,
                        "label_ids_ms": ids_ms,
                        "label_ratio": max(onehot_ms, ids_ms) / (1000 * plain),
                        "step_ms": 1000 * step,
                        "evals_per_s": stats.evaluations / plain if stats.evaluations else None,
                        "intersections": stats.intersections or None,
                    }
                )
    table = pd.DataFrame(rows)
    info = describe_device(devices[-1])
    print(
        f"torch {info['torch']}  cpu {info['cpu']} ({info['cpu_cores']} cores, "
        f"{info['torch_threads']} threads)" + (f"  gpu {info['gpu']}" if "gpu" in info else "")
    )
    print("960x540, median of", args.repeats, "runs after a warm-up\n")
    print(
        table.to_string(index=False, float_format=lambda v: f"{v:,.2f}" if v < 1e5 else f"{v:.3g}")
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    table.assign(**{k: str(v) for k, v in info.items()}).to_csv(args.out, index=False)
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
