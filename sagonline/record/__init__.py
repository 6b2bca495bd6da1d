"""Rerun recordings: a run's cameras, frames, masks, label renders and labelled Gaussians."""
