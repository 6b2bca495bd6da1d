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
# numpy's BLAS (OpenBLAS) on one thread: its idle threads spin after each product and take cores
# from torch's and the kernels' (on 2 cores a Stage I view's vote took 51-56 ms beside them
# against 39-40 ms, and a mask's 64x64 grid 2.4 ms after a torch call against 0.3 ms;
# docs/performance.md). The host's products are small (a mask on the feature grid, camera
# math), and one thread also gives the same products on any number of cores. OpenBLAS reads it
# when numpy loads; one already in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
