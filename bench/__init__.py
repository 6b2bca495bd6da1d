"""Hydra entry points (eval, ablations, timing) and report building. Thin by design."""

import sagonline  # noqa: F401, E402 (sets the OpenMP wait policy before torch loads)
