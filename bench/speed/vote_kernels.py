"""The Triton vote kernels side by side: the splat walk (`walk`, the default) and the chunked
vote (`chunk16`, `chunk32`), each on tile lists made by PyTorch (the default) or, with the
suffix `+fused`, by `triton_prepare`'s kernels, on `bench.speed.render`'s scenes: ms to make one
view's tile lists, ms per vote (tile lists included), `--masks` votes in a row, and whether
each histogram is the first row's (RGC counts: exactly).

    python -m bench.speed.vote_kernels [--device cuda] [--masks 206] [--repeats 5]
        [--kernels walk,walk+fused,chunk16,chunk16+fused,chunk32,chunk16w16] [--out F.csv]
        [--quick]

The kernel is chosen per vote by SAGONLINE_TRITON_VOTE (`render.backends.triton_vote_kernel`)
and the tile lists by SAGONLINE_TRITON_PREPARE (`render.backends.triton_prepare`), so every row
runs in one process on one machine: their ratio is the figure to read. On the CPU the kernels
run in Triton's interpreter (what the tests run, with --quick): its times say nothing of a GPU's.
"""

from __future__ import annotations

import argparse
import os
import time
from functools import partial
from pathlib import Path
from unittest import mock

import torch

from bench.speed.render import (
    RULE,
    aggregate,
    no_warmup,
    random_mask,
    scenes,
    show_table,
    timed,
)
from sagonline.render import vote_histogram
from sagonline.render.backends import TRITON_PREPARES, TRITON_VOTE_KERNELS
from sagonline.render.triton_prepare import chosen_tile_view

DEFAULT_KERNELS = "walk,walk+fused,chunk16,chunk16+fused,chunk32,chunk16w16"


def parse_kernel(spec: str) -> tuple[str, str]:
    """'chunk16+fused' -> ('chunk16', 'fused'); 'walk' -> ('walk', 'torch'). ValueError names
    what is not known."""
    kernel, _, prepare = spec.partition("+")
    prepare = prepare or "torch"
    if kernel not in TRITON_VOTE_KERNELS or prepare not in TRITON_PREPARES:
        raise ValueError(
            f"{spec!r}: a kernel of {tuple(TRITON_VOTE_KERNELS)}, optionally +fused (tile lists "
            f"by triton_prepare)"
        )
    return kernel, prepare


def vote_difference(
    hist: torch.Tensor,  # [N, L] a kernel's votes, a row per Gaussian
    first: torch.Tensor,  # [N, L] the first kernel's
) -> dict:
    """How many Gaussians' votes differ from the first kernel's, and of those how many lead
    with another label (their most-voted label differs; a Gaussian with no vote leads with
    none): whether a difference of a vote can change a label."""
    other = (hist != first).any(dim=1)
    lead = torch.where(hist.sum(1) > 0, hist.argmax(1), -1)
    lead_first = torch.where(first.sum(1) > 0, first.argmax(1), -1)
    return {
        "gaussians_voting_otherwise": int(other.sum()),
        "gaussians_leading_otherwise": int((lead != lead_first).sum()),
    }


def kernel_rows(
    name: str, g, views, kernels: list[str], masks: int, repeats: int, device: str, quick=False
):
    """One row per kernel ('walk', 'chunk16+fused': `parse_kernel`) on one scene: ms to make
    one view's tile lists, ms per vote (median of `repeats` after a warm-up), ms for `masks`
    votes in a row (after a warm-up over the views), and whether its histogram of one mask
    equals the first kernel's that ran (exact) or how far it is (largest difference); a kernel
    that fails has its error instead. `quick` (Triton's interpreter, which compiles nothing):
    no warm-ups, and the vote timed once, at its first call."""
    ring = [v.to(device) for v in views]
    mask_of = [random_mask(v) for v in ring]
    many = [mask_of[i % len(ring)] for i in range(masks)]
    rows, first, first_ms = [], None, None
    for kernel in kernels:
        vote_kernel, prepare = parse_kernel(kernel)
        row = {"scene": name, "device": device, "kernel": kernel, "masks": masks}
        chosen = {"SAGONLINE_TRITON_VOTE": vote_kernel, "SAGONLINE_TRITON_PREPARE": prepare}
        try:  # a kernel that fails to compile or run is a row that says so, not the end
            with mock.patch.dict(os.environ, chosen):
                bins = partial(chosen_tile_view(), g, ring[0], 0.01, with_colors=False)
                prepare_ms = 1000 * timed(bins, repeats, device, no_warmup if quick else None)
                vote = partial(vote_histogram, g, ring[0], mask_of[0], 3, RULE, backend="triton")
                start = time.perf_counter()
                hist = vote()  # also the vote's warm-up: its kernels are compiled now
                first_call_s = time.perf_counter() - start  # quick: the one call timed
                ms = 1000 * (first_call_s if quick else timed(vote, repeats, device, no_warmup))
                warm = (
                    no_warmup if quick else partial(aggregate, g, ring, many[: len(ring)], "triton")
                )
                all_ms = 1000 * timed(partial(aggregate, g, ring, many, "triton"), 1, device, warm)
        except Exception as exc:  # noqa: BLE001 (reported in the table)
            rows.append(row | {"error": f"{type(exc).__name__}: {exc}"[:300]})
            continue
        first = hist if first is None else first
        first_ms = ms if first_ms is None else first_ms
        rows.append(
            row
            | {
                "tile_lists_ms": prepare_ms,
                "vote_ms_per_mask": ms,
                "aggregate_ms": all_ms,
                "speedup_vs_first": first_ms / ms,
                "same_votes_as_first": bool(torch.equal(hist, first)),
                "max_difference": float((hist - first).abs().max()),
                **vote_difference(hist, first),
                "error": None,
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument(
        "--kernels",
        default=DEFAULT_KERNELS,
        help="the first is the base; a kernel's suffix +fused makes its tile lists in Triton",
    )
    ap.add_argument("--masks", type=int, default=206, help="votes in the aggregate column")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None, help="also write the table as a CSV")
    ap.add_argument(
        "--quick", action="store_true", help="the tiny scenes, 1 mask, 1 run, no warm-ups"
    )
    args = ap.parse_args()
    if args.quick:
        args.masks, args.repeats = 1, 1
    kernels = args.kernels.split(",")
    try:
        [parse_kernel(k) for k in kernels]
    except ValueError as exc:
        ap.error(f"--kernels {args.kernels!r}: {exc}")
    rows = []
    for name, g, _, views in scenes(args.quick):
        rows += kernel_rows(
            name,
            g.to(args.device),
            views,
            kernels,
            args.masks,
            args.repeats,
            args.device,
            quick=args.quick,
        )
    heading = f"Triton vote kernels on {{where}}; RGC, 3-label masks; median of {args.repeats}"
    table = show_table(rows, args.device, heading, args.out)
    if table["error"].notna().any():
        raise SystemExit("a kernel failed: its row says why")


if __name__ == "__main__":
    main()
