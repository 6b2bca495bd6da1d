"""Where one vote's time goes: `torch.profiler` around RGC votes of 3-label masks on the bench
scenes (`bench.speed.render`'s), per operator and kernel, so a vote above its target says what
bounds it (the projection, the tile lists, the walk, the histogram's atomics).

    python -m bench.speed.vote_profile [--device cuda] [--backend triton] [--masks 8]
                                       [--out reports/vote_profile_cuda.csv] [--quick]

Each scene's votes run once to warm up, then `--masks` votes are profiled; the table lists the
operators and kernels of largest self time (device time on CUDA, CPU time on the CPU) with
their calls and share of the total. On a GPU, `scripts/gpu_check.sh` also runs the votes under
Nsight Compute where `ncu` is installed (its speed-of-light and memory sections: memory,
atomics or occupancy), with `--plain`: Nsight Compute holds the GPU's counters, so
`torch.profiler` would see no kernel there; `--plain` runs the same votes without it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch

from bench.speed.render import RULE, random_mask, scenes
from sagonline.core.files import atomic_write_text
from sagonline.render import vote_histogram


def profile_votes(
    g, views, backend: str, masks: int, device: str, plain: bool = False
) -> pd.DataFrame | None:
    """The profiled votes' operators and kernels, largest self time first (ms in all); with
    `plain`, the votes alone (for an outside profiler) and None. ValueError where the profiler
    saw no time at all (another profiler holding the GPU's counters)."""
    from torch.profiler import ProfilerActivity, profile

    cams = [c.to(device) for c in views]
    mask_of = [random_mask(c) for c in cams]
    hist = torch.zeros(len(g), 3, dtype=torch.float64, device=device)

    def votes(n: int) -> None:
        for i in range(n):
            k = i % len(cams)
            vote_histogram(g, cams[k], mask_of[k], 3, RULE, backend=backend, out=hist)
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    votes(len(cams))  # warm: compile, tile buffers
    if plain:
        votes(masks)
        return None
    activities = [ProfilerActivity.CPU]
    cuda = device.startswith("cuda")
    if cuda:
        activities.append(ProfilerActivity.CUDA)
    with profile(activities=activities) as prof:
        votes(masks)
    rows = []
    for e in prof.key_averages():
        self_us = e.self_device_time_total if cuda else e.self_cpu_time_total
        if self_us <= 0:
            continue
        rows.append({"operator or kernel": e.key[:80], "calls": e.count, "self ms": self_us / 1e3})
    if not rows:
        raise ValueError(
            f"torch.profiler saw no {'device' if cuda else 'CPU'} time in {masks} votes: is "
            "another profiler (Nsight Compute) holding the counters? Under one, pass --plain"
        )
    table = pd.DataFrame(rows).sort_values("self ms", ascending=False)
    table["share %"] = (100 * table["self ms"] / table["self ms"].sum()).round(1)
    table["self ms per vote"] = (table["self ms"] / masks).round(3)
    return table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backend", default=None, help="the vote's backend (default: triton on CUDA)")
    ap.add_argument("--masks", type=int, default=8, help="votes profiled per scene (1-1000)")
    ap.add_argument("--top", type=int, default=12, help="rows shown per scene")
    ap.add_argument("--out", type=Path, default=None, help="also write the tables as one CSV")
    ap.add_argument("--quick", action="store_true", help="the tiny scenes (what the tests run)")
    ap.add_argument("--plain", action="store_true", help="the votes alone, for an outside profiler")
    args = ap.parse_args()
    if not 1 <= args.masks <= 1000:
        ap.error("--masks in [1, 1000]")
    backend = args.backend or ("triton" if args.device.startswith("cuda") else "native")
    tables = []
    for name, g, _, views in scenes(args.quick):
        try:
            table = profile_votes(
                g.to(args.device), views, backend, args.masks, args.device, args.plain
            )
        except ValueError as err:
            raise SystemExit(f"{name}: {err}") from None
        if table is None:
            print(f"{name}: {args.masks} votes, backend {backend} on {args.device}, not profiled")
            continue
        print(f"\n## {name}: {args.masks} votes, backend {backend} on {args.device}\n")
        print(table.head(args.top).to_markdown(index=False))
        tables.append(table.assign(scene=name, backend=backend, device=args.device))
    if args.out is not None and tables:
        atomic_write_text(args.out, pd.concat(tables).to_csv(index=False))


if __name__ == "__main__":
    main()
