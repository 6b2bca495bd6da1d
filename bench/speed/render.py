"""Rasterizer and vote speed: the image render, the vote per mask and over 206 masks (the paper's
Table III setting), the label renders, and the training step, per backend, beside the paper.

    python -m bench.speed.render [--repeats 3] [--devices cpu,cuda] [--masks 206]
                                 [--out reports/bench_render.csv] [--quick]

Scenes: the trained donut (3DGS, 45,624 Gaussians, from ../shared/data) and a generated 360-degree
2DGS scene of 200k surfels, both at 960x540. Backends: on the CPU the PyTorch reference (torch)
and the compiled kernels (native); on CUDA the reference, gsplat (images; its vote walks gsplat's
ids from Python) and the fused Triton kernel (vote and label renders; images from gsplat where it
is installed, else from the Triton walk's composite).
"vote ms/mask" is one RGC vote of a 3-label mask through the vote op (projection, tile lists,
walk, histogram); "vote speed-up" is the torch row's time over it; "aggregate ms" votes `--masks`
views in a row (the paper: 206 masks in 1466 ms on an RTX 4090, 7.1 ms/mask); "label" columns
are the label renders scoring uses (one-hot composite, most-visible ids) and "label ratio" the
slower one over the image render; "step" is forward + backward through every Gaussian
parameter, the fitting loop's inner cost (not for the vote-only Triton row). --quick: tiny
scenes at 96x54, 4 masks, one repeat (what the tests run: every line of this script, in seconds).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from functools import partial

import pandas as pd
import torch

from bench import OUT_HELP, REPORTS, ROOT
from sagonline.core.files import atomic_write_text
from sagonline.core.machine import describe_device
from sagonline.render import RasterStats, render, render_labels, vote_histogram
from sagonline.render.backends import installed
from sagonline.render.native import native_available, vote_simd
from sagonline.render.rule import VoteRule
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.generator import make_scene
from sagonline.scene.io import read_scene
from sagonline.scene.io.cameras import load_nerf_transforms

PAPER_MS_PER_MASK = 7.1  # the paper's Table III: RTX 4090, 960x540
PAPER_AGGREGATE_MS = 1466.0  # 206 masks
RULE = VoteRule()  # the paper's RGC: eps 0.01, delta 2 px, +1 per pair


def scenes(quick: bool = False):
    """(name, Gaussians, camera, views) of each scene timed: the trained donut and a generated
    200k-surfel 360 scene at 960x540 (quick: every 50th donut Gaussian and 4k surfels, 96x54)."""
    width, height = (96, 54) if quick else (960, 540)
    shared, carried = ROOT.parent / "shared" / "data", ROOT / ".gpu-bundle" / "data"
    donut_dir = next(
        (d / "donut_3dgs" for d in (shared, carried) if (d / "donut_3dgs").exists()),
        shared / "donut_3dgs",
    )  # the shared data beside the checkout, or the copy `make gpu-bundle` carries
    if donut_dir.exists():
        views = [
            c.scaled(width, height) for c in load_nerf_transforms(donut_dir / "transforms.json")
        ]
        g = read_scene(donut_dir / "point_cloud.ply")
        if quick:
            g = g.subset(torch.arange(0, len(g), 50))
        yield f"donut (3DGS, {len(g):,})", g, views[0], views
    else:
        print(f"note: {donut_dir} not found; skipping the donut", file=sys.stderr)
    count = 4_000 if quick else 200_000
    s = make_scene(layout="360", num_gaussians=count, width=width, height=height, num_train_views=4)
    name = f"synthetic 360 (2DGS, {len(s.gaussians):,})"
    yield name, s.gaussians, s.train_cameras[1], s.train_cameras


def training_step(g: Gaussians, cam, backend: str) -> None:
    """Render with every parameter requiring grad, then backward an L1 loss to a grey image."""
    leaves = {
        k: getattr(g, k).detach().clone().requires_grad_(True)
        for k in ("means", "quats", "scales", "opacities", "sh")
    }
    out = render(Gaussians(**leaves), cam, backend=backend)
    (out.rgb - 0.5).abs().mean().backward()


def random_mask(cam) -> torch.Tensor:
    gen = torch.Generator().manual_seed(0)
    return torch.randint(0, 3, (cam.height, cam.width), generator=gen).to(cam.K.device)


def aggregate(g: Gaussians, views, masks, backend: str) -> None:
    """One RGC vote of len(masks) masks into one histogram, as `consensus_vote` runs it."""
    hist = torch.zeros(len(g), 3, dtype=torch.float64, device=g.device)
    for i, mask in enumerate(masks):
        vote_histogram(g, views[i % len(views)], mask, 3, RULE, backend=backend, out=hist)


def label_render(g: Gaussians, cam, backend: str, mode: str) -> None:
    """One 3-label mask render (one-hot composite or most-visible ids), as scoring runs it."""
    labels = torch.arange(len(g), device=g.device) % 3
    render_labels(g, cam, labels, 3, mode=mode, backend=backend)


def backends(device: str, have=None) -> list[tuple[str, str]]:
    """(row name, image backend) per device; the row name is also the vote backend. `have`:
    what is installed (`render.backends.Installed`; this machine's by default)."""
    have = have or installed()
    if device == "cpu":
        return [("torch", "torch")] + ([("native", "native")] if have.has("native") else [])
    rows = [("torch", "torch")]
    if have.has("gsplat"):
        rows.append(("gsplat", "gsplat"))
    if have.has("triton"):
        rows.append(("triton", "gsplat" if have.has("gsplat") else "triton"))
    return rows


def cpu_walk_simd(devices: list[str]) -> str:
    """The compiled CPU walk's instruction set where the CPU was timed, else "-": asking builds
    the CPU kernels, a minute on a GPU machine whose run never uses them."""
    return vote_simd() if "cpu" in devices and native_available() else "-"


def show_table(rows: list[dict], device: str, heading: str, out=None) -> pd.DataFrame:
    """Print `rows` under `heading` (its {where}: the GPU's name, or the CPU with Triton's
    interpreter) and write them, with a `gpu` column, to the CSV `out` when given."""
    table = pd.DataFrame(rows)
    gpu = torch.cuda.get_device_name(0) if device.startswith("cuda") else None
    where = gpu or "the CPU, Triton's kernels in its interpreter (not a GPU's times)"
    print(heading.format(where=where) + "\n")
    print(table.to_markdown(index=False, floatfmt=".3g"))
    if out is not None:
        atomic_write_text(out, table.assign(gpu=gpu).to_csv(index=False))
    return table


def no_warmup() -> None:
    """`timed`'s warmup where the first call already ran (or Triton's interpreter, which
    compiles nothing, runs it)."""


def timed(fn, repeats: int, device: str, warmup=None) -> float:
    """Median seconds of `repeats` calls of `fn` after one call of `warmup` (default: `fn`)."""

    def sync():
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    (warmup or fn)()
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
    ap.add_argument("--masks", type=int, default=206, help="masks in the aggregation column")
    ap.add_argument("--out", default=str(REPORTS / "bench_render.csv"), help=OUT_HELP)
    ap.add_argument("--quick", action="store_true", help="tiny scenes, 4 masks, one repeat")
    ap.add_argument(
        "--no-reference-aggregate",
        action="store_true",
        help="leave the torch rows' aggregation column empty on CUDA too (206 reference votes "
        "take about 40 s per scene on an H100; the per-mask column still has them)",
    )
    args = ap.parse_args()
    if args.quick:
        args.repeats, args.masks = 1, 4
    devices = [d for d in args.devices.split(",") if d == "cpu" or torch.cuda.is_available()]
    if not devices:
        ap.error(f"--devices {args.devices}: none of them is here (no CUDA); add cpu")
    rows = []
    for name, gaussians, cam, views in scenes(args.quick):
        for device in devices:
            g, c = gaussians.to(device), cam.to(device)
            ring = [v.to(device) for v in views]
            masks = [random_mask(v) for v in ring]
            for backend, image_backend in backends(device):
                vote = partial(vote_histogram, g, c, masks[0], 3, RULE, backend=backend)
                vote_ms = 1000 * timed(vote, args.repeats, device)
                if backend == "torch":
                    torch_vote_ms = vote_ms
                many = [masks[i % len(masks)] for i in range(args.masks)]
                agg = partial(aggregate, g, ring, many, backend)
                aggregate_ms = None  # the reference over 206 masks: minutes on a CPU
                if backend != "torch" or (device == "cuda" and not args.no_reference_aggregate):
                    # warmed up on one pass over the ring, not a second run of all the masks
                    warm = partial(aggregate, g, ring, many[: len(ring)], backend)
                    aggregate_ms = 1000 * timed(agg, 1, device, warmup=warm)
                image_ms = 1000 * timed(
                    partial(render, g, c, backend=image_backend), args.repeats, device
                )
                onehot_ms, ids_ms = (
                    1000 * timed(partial(label_render, g, c, backend, mode), args.repeats, device)
                    for mode in ("onehot", "ids")
                )
                step = None
                if backend != "triton":
                    step = 1000 * timed(
                        partial(training_step, g, c, image_backend), args.repeats, device
                    )
                stats = RasterStats()
                if backend == "torch":
                    render(g, c, stats=stats)
                rows.append(
                    {
                        "scene": name,
                        "device": device,
                        "backend": backend,
                        "render_ms": image_ms,
                        "vote_ms_per_mask": vote_ms,
                        "vote_speedup": torch_vote_ms / vote_ms if backend != "torch" else None,
                        "masks": args.masks,
                        "aggregate_ms": aggregate_ms,
                        "label_onehot_ms": onehot_ms,
                        "label_ids_ms": ids_ms,
                        "label_ratio": max(onehot_ms, ids_ms) / image_ms,
                        "step_ms": step,
                        "evals_per_s": 1000 * stats.evaluations / image_ms
                        if stats.evaluations
                        else None,
                        "intersections": stats.intersections or None,
                        "paper_vote_ms_per_mask": PAPER_MS_PER_MASK,
                        "paper_aggregate_ms_206": PAPER_AGGREGATE_MS,
                    }
                )
    table = pd.DataFrame(rows)
    info = describe_device(devices[-1])
    simd = cpu_walk_simd(devices)
    print(
        f"torch {info['torch']}  cpu {info['cpu']} ({info['cpu_cores']} cores, "
        f"{info['torch_threads']} threads, vote walk {simd})"
        + (f"  gpu {info['gpu']}" if "gpu" in info else "")
    )
    size = f"{cam.width}x{cam.height}"
    print(f"{size}, median of {args.repeats} runs after a warm-up (aggregate: one run)")
    print("paper (RTX 4090, 960x540): 7.1 ms/mask, 206 masks in 1466 ms\n")
    shown = table.drop(columns=["paper_vote_ms_per_mask", "paper_aggregate_ms_206"])
    print(
        shown.to_string(index=False, float_format=lambda v: f"{v:,.2f}" if v < 1e5 else f"{v:.3g}")
    )
    table = table.assign(**{k: str(v) for k, v in info.items()})
    atomic_write_text(args.out, table.to_csv(index=False))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
