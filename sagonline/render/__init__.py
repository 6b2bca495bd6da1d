"""Rasterizers (the tiled PyTorch path, its brute-force reference, the compiled CPU kernel,
gsplat on CUDA) and the vote op, `vote_histogram`."""

from sagonline.render.api import render, render_labels
from sagonline.render.projection import ProjectedSplats, project
from sagonline.render.rasterize import (
    RasterStats,
    RenderOutput,
    TraceChunk,
    TraceRequest,
    rasterize,
)
from sagonline.render.vote import vote_histogram

__all__ = [
    "ProjectedSplats",
    "RasterStats",
    "RenderOutput",
    "TraceChunk",
    "TraceRequest",
    "project",
    "rasterize",
    "render",
    "render_labels",
    "vote_histogram",
]
