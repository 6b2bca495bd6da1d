"""What to segment and who segments it: prompts, the clicks of a command line or a viewer, and
the 2D video segmenters behind one interface (see `base.VideoSegmenter`)."""

from sagonline.segment.base import SegmentationResult, VideoSegmenter
from sagonline.segment.oracle import OracleSegmenter
from sagonline.segment.prompts import ObjectPrompt, Prompt

__all__ = ["ObjectPrompt", "OracleSegmenter", "Prompt", "SegmentationResult", "VideoSegmenter"]
