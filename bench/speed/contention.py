"""Two votes at once on shared cores: each one's ms per mask against the same vote alone.

    python -m bench.speed.contention [--masks 5] [--out reports/bench_contention.csv] [--quick]

Parallel sweeps (`LAUNCHER=local`), Stage II training beside the initial mode and shared cluster
nodes all run a vote beside other work. For each backend (torch: the tiled PyTorch trace reduced
by the vote's accumulator; native: the compiled trace-and-vote kernel) and thread count, the
vote pass on the donut at 960x540 (the generated 200k-surfel scene when the donut is absent) is
timed alone in this process, then in two processes started together (each waits at a barrier
until both have loaded the scene and warmed up); "slowdown" is the median
per-mask time together over alone. Numbers depend on what else the machine runs: the table's
header says how many cores there are and the load before it started. --quick: the small
scenes of `bench.speed.render --quick`, 2 masks, one thread count (what the tests run).
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics

import pandas as pd

from bench import OUT_HELP, REPORTS
from sagonline.core.files import atomic_write_text


def scene(quick: bool = False):
    """The first scene `make bench` times: the donut, else the generated 200k-surfel scene."""
    from bench.speed.render import scenes

    return next(scenes(quick))


def vote_times(backend: str, threads: int, masks: int, start=None, quick: bool = False) -> list:
    """ms per mask of `masks` RGC votes (after one warm-up), optionally waiting at the
    `start` barrier first, so that two processes start together once both are ready."""
    import torch

    from sagonline.vote.consensus import VoteConfig, consensus_vote

    torch.set_num_threads(threads)
    _, g, cam, _ = scene(quick)
    gen = torch.Generator().manual_seed(0)
    mask = torch.randint(0, 3, (cam.height, cam.width), generator=gen).numpy()
    run = lambda n: consensus_vote(g, [cam] * n, [mask] * n, 3, VoteConfig(), backend=backend)  # noqa: E731
    run(1)
    if start is not None:
        start.wait()
    return [run(1).stats["ms_per_mask"] for _ in range(masks)]


def _child(args, queue) -> None:
    queue.put(vote_times(*args))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--masks", type=int, default=5)
    ap.add_argument("--out", default=str(REPORTS / "bench_contention.csv"), help=OUT_HELP)
    ap.add_argument("--quick", action="store_true", help="small scenes, 2 masks, 1 thread")
    args = ap.parse_args()
    if args.quick:
        args.masks = 2
    from sagonline.core.machine import describe_device
    from sagonline.render.native import native_available

    backends = ["torch"] + (["native"] if native_available() else [])
    cores = os.cpu_count() or 1
    load = os.getloadavg()[0]
    ctx = mp.get_context("spawn")
    rows = []
    for backend in backends:
        for threads in [1] if args.quick else sorted({1, cores}):
            alone = statistics.median(vote_times(backend, threads, args.masks, quick=args.quick))
            queue = ctx.Queue()
            start = ctx.Barrier(2)  # each child passes once it has loaded and warmed up
            job = (backend, threads, args.masks, start, args.quick)
            procs = [ctx.Process(target=_child, args=(job, queue)) for _ in range(2)]
            for p in procs:
                p.start()
            together = [statistics.median(queue.get()) for _ in procs]
            for p in procs:
                p.join()
            rows.append(
                {
                    "backend": backend,
                    "threads_per_vote": threads,
                    "alone_ms_per_mask": alone,
                    "together_ms_per_mask": max(together),
                    "slowdown": max(together) / alone,
                }
            )
    table = pd.DataFrame(rows)
    info = describe_device("cpu")
    name, _, cam, _ = scene(args.quick)
    where = f"cpu {info['cpu']} ({cores} cores), load before {load:.2f}"
    print(f"{name} at {cam.width}x{cam.height}; {where}")
    print(f"median of {args.masks} masks; together = the slower of two votes started at once\n")
    print(table.to_string(index=False, float_format=lambda v: f"{v:,.2f}"))
    table = table.assign(cpu=info["cpu"], cores=cores, load_before=load)
    atomic_write_text(args.out, table.to_csv(index=False))
    print(f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
