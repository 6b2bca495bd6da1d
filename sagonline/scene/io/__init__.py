"""File formats: Gaussian scenes (PLY, .splat), camera files, image folders.

Each name is imported from its module when first read, so a command that needs only the image
or PLY readers (`sagonline score --help`) does not import PyTorch with the camera files."""

from __future__ import annotations

from typing import TYPE_CHECKING

from sagonline.core.lazy import lazy_names

# name -> the module of this package that defines it
WHERE = {
    "CameraFileError": "cameras",
    "load_cameras": "cameras",
    "write_3dgs_cameras_json": "cameras",
    "IMAGE_SUFFIXES": "images",
    "NEAREST_SAMPLING": "images",
    "list_images": "images",
    "resize_nearest": "images",
    "SceneFileError": "ply",
    "fitted_background": "ply",
    "read_scene": "ply",
    "scene_file": "ply",
    "write_ply": "ply",
    "read_splat": "splat",
}

if TYPE_CHECKING:
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


__getattr__ = lazy_names(__name__, WHERE)


__all__ = [
    "CameraFileError",
    "IMAGE_SUFFIXES",
    "NEAREST_SAMPLING",
    "SceneFileError",
    "fitted_background",
    "list_images",
    "load_cameras",
    "read_scene",
    "read_splat",
    "resize_nearest",
    "scene_file",
    "write_3dgs_cameras_json",
    "write_ply",
]
