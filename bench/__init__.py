"""Hydra entry points (eval, ablations, timing) and report building. Thin by design."""
