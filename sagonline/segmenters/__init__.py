"""2D video segmenters behind one interface (see `base.VideoSegmenter`)."""

from sagonline.prompts import ObjectPrompt, Prompt
from sagonline.segmenters.base import SegmentationResult, VideoSegmenter
from sagonline.segmenters.oracle import OracleSegmenter

__all__ = ["ObjectPrompt", "OracleSegmenter", "Prompt", "SegmentationResult", "VideoSegmenter"]
