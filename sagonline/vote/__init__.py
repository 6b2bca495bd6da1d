"""Stage I's lift: 2D masks voted into one label per Gaussian (`consensus`), the optional fill
from labelled neighbours, and consensus feedback (which mask a view votes with)."""
