"""File formats: Gaussian scenes (PLY, .splat) and raw <-> activated parameter conversion."""

from sagonline.io.ply import SceneFileError, read_scene, read_splat, write_ply

__all__ = ["SceneFileError", "read_scene", "read_splat", "write_ply"]
