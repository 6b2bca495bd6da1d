"""Rasterizers: the tiled PyTorch fast path, its brute-force reference, and gsplat on CUDA."""

from sagonline.render.api import render, render_labels
from sagonline.render.projection import ProjectedSplats, project
from sagonline.render.rasterize import (
    RasterStats,
    RenderOutput,
    TraceChunk,
    TraceRequest,
    rasterize,
)

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
]
