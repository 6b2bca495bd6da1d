"""2D video segmenters behind one interface (see `base.VideoSegmenter`)."""

from sagonline.segmenters.base import ObjectPrompt, Prompt, SegmentationResult, VideoSegmenter
from sagonline.segmenters.oracle import OracleSegmenter

__all__ = ["ObjectPrompt", "OracleSegmenter", "Prompt", "SegmentationResult", "VideoSegmenter"]
