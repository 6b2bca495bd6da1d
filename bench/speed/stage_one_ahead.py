"""Stage I per view with each next view's encoder started ahead (`segmenter.encode_ahead`) and
without, on one model in one process, the two in turns: each view's wall time from the moment
the view before it was done (its labels read back) to its own labels read back, with nothing
synchronised in between, so that what the side stream overlaps shows.

    python -m bench.speed.stage_one_ahead [--device cuda] [--segmenter sam2_tiny]
        [--objects 1] [--views 24] [--rounds 2] [--option KEY=VALUE] [--out F.csv] [--quick]

The scene, the prompt, the options and the fused labels' advice are `bench.speed.stage_one`'s
(the frames rendered when the segmenter asks for them, the embedding cache off and the model's
embeddings forgotten before each pass); its per-part columns wait for the GPU after every part,
which would hide the overlap, so here only each view's total is timed. A first round of both is
run untimed (the CUDA graphs' captures, the first calls of each path). Started ahead, a view's
time holds the next view's encoder (the first view after the prompt's holds two, the last none),
so the passes compare by their whole time a view; the median of views 1.. is the steady state.
--quick: 3 views at 96x54, 4k surfels, one round and no untimed one (the tests').
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench.speed.stage_one import (
    Clock,
    RenderedOnAsk,
    advice_for,
    build,
    scene_and_prompt,
    view_arguments,
    views_asked,
    weights_named,
)
from sagonline.core.files import atomic_write_text
from sagonline.vote.consensus import VoteAccumulator, VoteConfig


def time_arms(
    segmenter_name: str,
    views: int,
    size,
    gaussians: int,
    objects: int,
    device: str,
    settings: dict,
    rounds: int,
    untimed: int = 1,
) -> tuple[pd.DataFrame, str]:
    """Rows (round, encode_ahead, view, ms) of `rounds` timed rounds, each a pass without and
    a pass with encoding ahead, after `untimed` rounds (0 or 1); and the weights that ran (each
    file's name and sha256 prefix)."""
    g, cams, plan, prompt = scene_and_prompt(views, size, gaussians, objects, device)
    segmenter = build(segmenter_name, device, settings)
    model = segmenter.model() if hasattr(segmenter, "model") else None
    if model is None:
        raise ValueError(f"segmenter {segmenter_name} has no image encoder to start ahead")
    rows = []
    for round_ in range(1 - untimed, rounds + 1):
        for ahead in (False, True):
            model.memory.clear()  # every view encoded again, as in the pass before
            segmenter.cfg.encode_ahead = ahead
            clock = Clock(device, synced=False)  # nothing waits for the GPU within a pass
            frames = RenderedOnAsk(g, cams, plan.images, clock)
            votes = VoteAccumulator(len(g), prompt.num_labels, VoteConfig(), device=device)
            advice = advice_for(segmenter, g, cams, votes, plan.vote, clock)  # as Stage I's
            if device.startswith("cuda"):
                torch.cuda.synchronize()  # between passes only
            last = time.perf_counter()
            for index, mask, _ in segmenter.stream(frames, prompt, advice=advice):
                votes.grow(int(mask.max()) + 1)
                votes.add_view(g, cams[index], mask, plan.vote, frame=index)
                votes.labels().cpu()  # read back, as Stage I publishes them
                now = time.perf_counter()
                if round_:
                    rows.append(
                        {"round": round_, "encode_ahead": ahead, "view": index}
                        | {"ms": 1000 * (now - last)}
                    )
                last = now
    return pd.DataFrame(rows), weights_named(segmenter)


def summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per pass kind: the median ms of views 1.. and the whole pass's ms a view, the prompt
    view's included (where started ahead, a view's time holds the next view's encoder, not its
    own: the first after the prompt view's holds two, the last none; the whole pass counts each
    once), and that
    over the plain passes' (ratio)."""
    rows = []
    for ahead, part in table.groupby("encode_ahead", sort=True):
        later = part[part.view != 0]
        rows.append(
            {"encode_ahead": bool(ahead), "passes": part["round"].nunique()}
            | {"median ms (views 1..)": later.ms.median()}
            | {"pass ms a view": part.ms.sum() / len(part)}
        )
    out = pd.DataFrame(rows)
    plain = out.loc[~out.encode_ahead, "pass ms a view"]
    out["ratio"] = out["pass ms a view"] / (plain.iloc[0] if len(plain) else np.nan)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    view_arguments(ap, "sam2_tiny", views=24, objects=1)
    ap.add_argument("--rounds", type=int, default=2, help="timed rounds of both passes")
    ap.add_argument("--out", type=Path, default=None, help="also write the per-view CSV")
    args = ap.parse_args()
    asked = views_asked(ap, args)
    rounds, untimed = (1, 0) if args.quick else (args.rounds, 1)
    if rounds < 1:
        ap.error("--rounds >= 1")
    try:
        table, weights = time_arms(*asked, rounds, untimed)
    except ValueError as exc:  # a missing model file names the option and `make weights`
        raise SystemExit(f"stage_one_ahead: {exc}") from None
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None
    print(
        f"Stage I per view, the next view encoded ahead or not: {args.segmenter} (weights: "
        f"{weights})"
        + "".join(f", {o}" for o in args.option)
        + f" on {gpu or args.device}, {args.views} views at {args.size}, {args.gaussians:,} "
        f"surfels, {args.objects} object(s), {rounds} round(s) after {untimed} untimed\n"
    )
    print(summary(table).round(3).to_markdown(index=False))
    if args.out is not None:
        named = {"segmenter": args.segmenter, "weights": weights}
        named |= {"options": " ".join(args.option)}
        named |= {"objects": args.objects, "size": args.size, "gpu": gpu}
        atomic_write_text(args.out, table.assign(**named).to_csv(index=False))


if __name__ == "__main__":
    main()
