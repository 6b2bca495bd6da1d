"""What to segment and who segments it: prompts, the clicks of a command line or a viewer, and
the 2D video segmenters behind one interface (see `base.VideoSegmenter`).

Each name is imported from its module when first read (`core.lazy`): the command line's
prompt parsing (`segment.clicks`) needs neither PyTorch nor OpenCV."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sagonline.core.lazy import lazy_names

# name -> the module of this package that defines it
WHERE = {
    "SegmentationResult": "base",
    "VideoSegmenter": "base",
    "OracleSegmenter": "oracle",
    "ObjectPrompt": "prompts",
    "Prompt": "prompts",
}

if TYPE_CHECKING:
    from sagonline.segment.base import SegmentationResult, VideoSegmenter
    from sagonline.segment.oracle import OracleSegmenter
    from sagonline.segment.prompts import ObjectPrompt, Prompt


__getattr__ = lazy_names(__name__, WHERE)


__all__ = ["ObjectPrompt", "OracleSegmenter", "Prompt", "SegmentationResult", "VideoSegmenter"]
