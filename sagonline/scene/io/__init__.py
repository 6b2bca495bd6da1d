"""File formats: Gaussian scenes (PLY, .splat), camera files, image folders."""

from sagonline.scene.io.cameras import CameraFileError, load_cameras, write_3dgs_cameras_json
from sagonline.scene.io.images import (
    IMAGE_SUFFIXES,
    NEAREST_SAMPLING,
    list_images,
    resize_nearest,
)
from sagonline.scene.io.ply import (
    SceneFileError,
    fitted_background,
    read_scene,
    scene_file,
    write_ply,
)
from sagonline.scene.io.splat import read_splat

__all__ = [
    "IMAGE_SUFFIXES",
    "CameraFileError",
    "SceneFileError",
    "fitted_background",
    "list_images",
    "load_cameras",
    "read_scene",
    "read_splat",
    "scene_file",
    "NEAREST_SAMPLING",
    "resize_nearest",
    "write_3dgs_cameras_json",
    "write_ply",
]
