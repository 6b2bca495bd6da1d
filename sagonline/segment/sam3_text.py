"""SAM 3 with text prompts: open-vocabulary semantic segmentation (extra: `.[sam3]`, CUDA).

Each frame is segmented independently by SAM 3's image model for every text (label i+1 is
`prompt.texts[i]`, e.g. UDD's classes): instance masks above `confidence` are merged into one
label map, the most confident instance on top. The semantic labels need no tracking, so the
video order only matters for the vote that follows.

Requirements, checked with clear messages: the `sam3` package (it imports `triton`), a local
checkpoint (`checkpoint`, e.g. sam3.pt; nothing is downloaded) and CUDA: sam3 0.1.4 builds its
position encodings with device="cuda" hard-coded (sam3/model/position_encoding.py), so the model
cannot be constructed on a CPU-only torch.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sagonline.core.plugins import SEGMENTERS
from sagonline.scene.io.checkpoints import load_user_checkpoint
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import Prompt


def merge_text_masks(
    shape: tuple[int, int], per_text: list[tuple[np.ndarray, np.ndarray]], confidence: float
) -> np.ndarray:
    """Label map from per-text detections.

    per_text[i] = (masks (K, H, W) bool, scores (K,)) for label i + 1. Instances below
    `confidence` are dropped; the rest are painted in order of increasing score.
    """
    out = np.zeros(shape, np.int64)
    painted = []
    for i, (masks, scores) in enumerate(per_text):
        for m, s in zip(masks, scores, strict=True):
            if s >= confidence:
                painted.append((float(s), i + 1, np.asarray(m, bool)))
    for _, label, m in sorted(painted, key=lambda t: t[0]):
        if m.shape != shape:
            raise RuntimeError(f"SAM 3 mask is {m.shape}, frame is {shape}")
        out[m] = label
    return out


@dataclass
class SAM3Config:
    """SAM 3's settings (`segmenter=sam3`; CUDA only)."""

    checkpoint: str | None = None
    """REQUIRED: a local checkpoint, e.g. /path/to/sam3.pt (nothing is downloaded)."""
    bpe_path: str | None = None
    """The tokenizer vocabulary; None: the one shipped in the sam3 package."""
    device: str = "cuda"
    """Where the model runs (sam3 builds on CUDA only)."""
    confidence: float = 0.5
    """Instances below this score are dropped."""
    trust_checkpoint: bool = False
    """Skip the weights_only check (only for files you trust; never taken from a run folder)."""

    def __post_init__(self) -> None:
        from sagonline.core.settings import check_settings

        c = self.confidence
        check_settings("segmenter", confidence=(0 <= c <= 1, c, "in [0, 1]"))


@SEGMENTERS.register("sam3", SAM3Config)
class SAM3TextSegmenter(VideoSegmenter):
    """SAM 3 text prompts: open-vocabulary masks from a local checkpoint (extra: .[sam3])."""

    name = "sam3"
    reads = ("text",)

    def __init__(
        self,
        checkpoint: str | None = None,
        bpe_path: str | None = None,
        device: str = "cuda",
        confidence: float = 0.5,
        trust_checkpoint: bool = False,
    ):
        if checkpoint is None:
            raise ValueError(
                "segmenter 'sam3' needs a local checkpoint: set "
                "segmenter.checkpoint=/path/to/sam3.pt (nothing is downloaded)"
            )
        if not Path(checkpoint).is_file():
            raise FileNotFoundError(f"segmenter.checkpoint={checkpoint}: no such file")
        self.checkpoint, self.bpe_path = checkpoint, bpe_path
        self.device, self.confidence = device, confidence
        self.trust_checkpoint = trust_checkpoint
        self._processor = None

    def weight_files(self) -> list[str]:
        return [self.checkpoint]

    def check(self) -> None:
        """The checkpoint must load with weights_only=True (tensors only) unless trusted."""
        if not self.trust_checkpoint:
            load_user_checkpoint(
                self.checkpoint, "segmenter.checkpoint", trust_option="segmenter.trust_checkpoint"
            )

    def build(self):
        from sagonline.segment.compat import import_torchvision

        if not (str(self.device).startswith("cuda") and torch.cuda.is_available()):
            raise RuntimeError(
                "segmenter 'sam3' needs CUDA: sam3 builds its position encodings "
                "on device='cuda' unconditionally"
            )
        self.check()
        try:
            import_torchvision()
            from sam3.model.sam3_image_processor import Sam3Processor
            from sam3.model_builder import build_sam3_image_model
        except ImportError as exc:
            raise RuntimeError(
                "segmenter 'sam3' needs the sam3 package (and triton): pip install -e '.[sam3]'"
            ) from exc
        model = build_sam3_image_model(
            bpe_path=self.bpe_path,
            device=self.device,
            checkpoint_path=self.checkpoint,
            load_from_HF=False,
        )
        self._processor = Sam3Processor(
            model, device=self.device, confidence_threshold=self.confidence
        )
        return self._processor

    def _segment(self, frames, prompt: Prompt, ground_truth):
        from PIL import Image

        if not prompt.texts:
            raise ValueError("segmenter 'sam3' needs text prompts (the dataset's class names)")
        proc = self._processor or self.build()
        masks, seconds = [], []
        for frame in frames:
            start = time.perf_counter()
            state = proc.set_image(Image.fromarray(frame))
            per_text = []
            for text in prompt.texts:
                out = proc.set_text_prompt(prompt=text, state=state)
                m = (
                    out["masks"].squeeze(1).cpu().numpy()
                    if len(out["masks"])
                    else np.zeros((0, *frame.shape[:2]), bool)
                )
                per_text.append((m, out["scores"].float().cpu().numpy()))
            masks.append(merge_text_masks(frame.shape[:2], per_text, self.confidence))
            seconds.append(time.perf_counter() - start)
        return masks, seconds
