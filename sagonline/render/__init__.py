"""Rasterizers (the tiled PyTorch path, its brute-force reference, the compiled CPU kernel,
gsplat on CUDA) and the vote op, `vote_histogram`. The rasterizer itself is
`render.rasterize.rasterize` (a name of the package would be shadowed by its module).

Each name is imported from its module when first read (`core.lazy`): the rules of
`render.rule` (the vote's, the label render's) are read without PyTorch."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sagonline.core.lazy import lazy_names

# name -> the module of this package that defines it
WHERE = {
    "render": "api",
    "render_labels": "api",
    "ProjectedSplats": "projection",
    "project": "projection",
    "RasterStats": "rasterize",
    "RenderOutput": "rasterize",
    "TraceChunk": "rasterize",
    "TraceRequest": "rasterize",
    "vote_histogram": "vote",
}

if TYPE_CHECKING:
    from sagonline.render.api import render, render_labels
    from sagonline.render.projection import ProjectedSplats, project
    from sagonline.render.rasterize import (
        RasterStats,
        RenderOutput,
        TraceChunk,
        TraceRequest,
    )
    from sagonline.render.vote import vote_histogram


__getattr__ = lazy_names(__name__, WHERE)


__all__ = [
    "ProjectedSplats",
    "RasterStats",
    "RenderOutput",
    "TraceChunk",
    "TraceRequest",
    "project",
    "render",
    "render_labels",
    "vote_histogram",
]
