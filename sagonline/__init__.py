"""SAGOnline: segment any Gaussians online.

Data flow: scene + cameras -> trajectory -> rasterizer (RGB + per-pixel trace) -> 2D video
segmenter -> rasterization-aware consensus vote -> one label per Gaussian -> label renders,
refinement student, metrics, reports.
"""

__version__ = "0.1.0"
