"""SAGOnline: segment any Gaussians online.

Data flow: scene + cameras -> trajectory -> rasterizer (RGB + per-pixel trace) -> 2D video
segmenter -> rasterization-aware consensus vote -> one label per Gaussian -> label renders,
refinement student, metrics, reports.
"""

import os

# OpenMP threads that finish early block instead of spinning: a spinning pool fights any other
# process on shared cores (two votes at once on 2 cores: 8.5x slower each, against 1.7x with
# this; bench/speed/contention.py). libgomp reads it when torch loads, so it is set before that;
# an OMP_WAIT_POLICY already in the environment wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
