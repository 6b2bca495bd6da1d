"""Following a view's objects into the next view: each object's candidate masks (the module
docstring of `sam_family`) from a few decoder prompts, the one most like its prototype kept.

An object's candidates come in up to three rounds of prompts, each round asked after the one
before it answered: its clicks, the blob's box and the fused labels' box; the clicks' mask again
with its own box and logits; its part without cells far less like it. `follow` is one object's
rounds as a generator of prompts; `follow_together` runs every object's rounds at once, so each
round of a view's objects is one `SamPair.decode_many` (with `segmenter.batch_prompts`, one
decoder call for each shape of prompt, not one a prompt)."""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass

import numpy as np

from sagonline.segment.decoder_prompts import DecoderPrompt
from sagonline.segment.embedding import GRID
from sagonline.segment.mask_geometry import box_of, interior_point, otsu
from sagonline.segment.sam_onnx import Answer, Embedding, SamPair

Found = tuple[np.ndarray, np.ndarray | None]  # [H, W] bool mask, its mean feature [C] or None
Rounds = Generator[list[DecoderPrompt], list[list[Answer]], Found]


@dataclass(frozen=True)
class Rules:
    """The prompting settings following reads (`SamPromptingConfig`'s of the same names)."""

    prompts: str  # match, match+3d or 3d
    refine: str  # before-advice or always
    min_similarity: float


@dataclass(frozen=True)
class Track:
    """One object as the view before left it."""

    prototype: np.ndarray | None  # [C] unit; None: not followed
    render: np.ndarray | None  # [H, W] bool, the fused labels' mask of it in this view
    level: int  # which of the decoder's masks it is (SAM 2: 0 whole ... 2 sub-part)
    max_area: float | None  # pixels a candidate may cover where a smaller one stands


def follow_together(
    model: SamPair, emb: Embedding, tracks: dict[int, Track], rules: Rules
) -> dict[int, Found]:
    """Every object's `follow` by label, each round of prompts of all the objects decoded at
    once."""
    running = {k: follow(emb, track, model.levels, rules) for k, track in tracks.items()}
    found: dict[int, Found] = {}
    asked: dict[int, list[DecoderPrompt]] = {}
    answers: dict[int, list[list[Answer]] | None] = dict.fromkeys(running)
    while True:
        for k in list(running):
            try:
                asked[k] = running[k].send(answers[k])
            except StopIteration as done:
                found[k] = done.value
                del running[k]
        if not running:
            return found
        order = list(running)
        flat = model.decode_many(emb, [p for k in order for p in asked[k]])
        start = 0
        for k in order:
            answers[k], start = flat[start : start + len(asked[k])], start + len(asked[k])


def follow(emb: Embedding, track: Track, levels: int, rules: Rules) -> Rounds:
    """One object's candidates in a later view (the decoder's mask at its `level` of each
    prompt), the one most like the prototype; candidates of more than `max_area` pixels only
    where none is smaller. Yields each round's prompts, is sent their answers, and returns
    the mask and its mean feature (an empty mask and None where nothing is like it)."""
    empty: Found = (np.zeros(emb.size, bool), None)
    if track.prototype is None:
        return empty
    sim = np.where(emb.valid(), emb.similarity(track.prototype), np.nan)
    if not np.isfinite(sim).any():
        return empty
    best, worst = int(np.nanargmax(sim)), int(np.nanargmin(sim))
    click = emb.cell_centre(best)
    use_render = track.render is not None and track.render.any()
    clicks = rules.prompts != "3d" or not use_render
    points = np.stack([click, emb.cell_centre(worst)])
    # the similarity blob's box with the best click (B): a decoder of one level only; SAM 2's
    # levels already hold what it adds (on the shared captures' photographs it changed the
    # masks by -0.03 to +0.41 IoU points, one decoder call a view)
    blob = blob_box(sim, best, emb) if clicks and levels == 1 else None
    first = [DecoderPrompt(points, np.array([1, 0]))] if clicks else []
    if blob is not None:
        first.append(DecoderPrompt(click[None], np.array([1]), blob))
    if use_render:
        inside = interior_point(track.render)
        first.append(DecoderPrompt(inside[None], np.array([1]), box_of(track.render)))

    def at_level(answers: list[Answer]) -> Answer:  # SAM answers one level, SAM 2 three
        return answers[min(track.level, len(answers) - 1)]

    picked = [at_level(a) for a in (yield first)]
    candidates = []  # (mask, its grid cells where known)
    if clicks:
        a = picked[0]
        if a.mask.any() and (rules.refine == "always" or not use_render):
            (again,) = yield [DecoderPrompt(points, np.array([1, 0]), box_of(a.mask), a.logits)]
            a = at_level(again)
        cells = emb.grid_mask(a.mask)  # once, for its part and for its likeness
        candidates.append((a.mask, cells))
        part = part_prompt(emb, sim, click, cells)
        if part is not None:
            (answer,) = yield [part]
            candidates.append((at_level(answer).mask, None))
    candidates += [(a.mask, None) for a in picked[1 if clicks else 0 :]]  # B's, C's
    return most_alike(emb, candidates, track, rules.min_similarity) or empty


def most_alike(emb: Embedding, candidates: list, track: Track, least: float) -> Found | None:
    """Of (mask, cells or None) candidates (those within `max_area`, else all), the mask whose
    mean feature is most like the prototype, with that feature; None where none is at least
    `least` like."""
    within = [
        c for c in candidates if track.max_area is None or np.count_nonzero(c[0]) <= track.max_area
    ]
    scored = []
    for mask, cells in within or candidates:
        feature = emb.mean_feature(mask, cells)
        if feature is not None:
            scored.append((float(feature @ track.prototype), mask, feature))
    if not scored:
        return None
    score, mask, feature = max(scored, key=lambda s: s[0])
    return (mask, feature) if score >= least else None


def part_prompt(
    emb: Embedding,
    sim: np.ndarray,  # [64, 64] similarity to the object, NaN off the image
    click: np.ndarray,  # [2] image pixels
    cells: np.ndarray,  # [64, 64] bool, a mask's `grid_mask`
) -> DecoderPrompt | None:  # None where the mask is of one appearance
    """A decoder answers with the largest thing a click lies on (the whole donut for a click
    on its icing): where the mask holds cells far less like the object than the clicked one,
    the prompt for its answers without them (a negative click on the least like)."""
    cells = cells & np.isfinite(sim)
    if not cells.any():
        return None
    inside = np.where(cells, sim, np.inf)
    least = int(np.argmin(inside))
    if np.nanmax(sim) - inside.flat[least] < 0.3:  # the mask is of one appearance
        return None
    return DecoderPrompt(np.stack([click, emb.cell_centre(least)]), np.array([1, 0]))


def blob_box(sim: np.ndarray, best: int, emb: Embedding) -> np.ndarray | None:  # [4] or None
    """The box (image pixels) of the Otsu blob of the similarity map around the best cell."""
    import cv2

    values = sim[np.isfinite(sim)]
    above = np.nan_to_num(sim, nan=-1.0) > otsu(values)
    count, comp = cv2.connectedComponents(above.astype(np.uint8))
    gy, gx = divmod(best, GRID)
    if count < 2 or comp[gy, gx] == 0:
        return None
    ys, xs = np.nonzero(comp == comp[gy, gx])
    box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32) * 16
    return box / np.array([*emb.scale, *emb.scale], np.float32)
