"""Scoring: 2D and 3D label metrics, the scored label maps as files, and the diagnosis of every
wrong pixel (fit, vote or segmenter)."""
