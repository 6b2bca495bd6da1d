"""Sparse points from posed images: SIFT features, exhaustive matching and triangulation with
the cameras held fixed (COLMAP's point triangulator, through pycolmap).

For captures that come with poses but no point cloud (LLFF `poses_bounds.npy`, NeRF
`transforms.json`), this gives `make scenes` the same kind of start a COLMAP scene has:
3D points on the textured surfaces, coloured from the images. Nothing is estimated but the
points: intrinsics and poses stay as the dataset gives them.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np

from sagonline.scene.cameras import Camera
from sagonline.scene.io.images import image_size

log = logging.getLogger(__name__)


def triangulate_known_poses(
    cameras: list[Camera],
    image_paths: dict[str, Path],
    *,
    max_features: int = 8192,
    peak_threshold: float = 0.0066667,  # COLMAP's default, 0.02 / octave_resolution (3)
    guided_matching: bool = False,
    two_view_tracks: bool = True,
    num_threads: int = 1,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Triangulate SIFT matches between `cameras` (all sharing one image folder and one set of
    intrinsics up to scale) with their poses fixed.

    image_paths: view name -> image file. Returns (P, 3) xyz, (P, 3) rgb in [0, 1] and a summary
    (points, mean track length, mean reprojection error in pixels). Deterministic by default:
    COLMAP's random seed is `seed`, and extraction, matching and triangulation run on
    `num_threads` (1: the same points every time; more threads finish sooner but assign image
    ids and verify pairs in a varying order).

    Why one function: it is one pycolmap session (database, features, matches, the fixed-pose
    reconstruction) whose steps share its temporary folder and image ids."""
    import pycolmap

    views = [c for c in cameras if c.name in image_paths]
    if len(views) < 2:
        raise ValueError(f"triangulation needs at least two posed images, got {len(views)}")
    folders = {image_paths[c.name].parent for c in views}
    if len(folders) != 1:
        raise ValueError(f"images for triangulation must share one folder, got {sorted(folders)}")
    folder = folders.pop()
    sizes = {}
    for c in views:
        sizes[c.name] = image_size(image_paths[c.name])
    # the cameras may be at another resolution than the files: scale the intrinsics per view
    pinhole = {}
    for c in views:
        w, h = sizes[c.name]
        K = c.K.double().numpy()
        sx, sy = w / c.width, h / c.height
        pinhole[c.name] = (w, h, [K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy])
    shared = len({(w, h, tuple(np.round(p, 6))) for w, h, p in pinhole.values()}) == 1

    pycolmap.set_random_seed(seed)
    work = Path(tempfile.mkdtemp(prefix="sagonline_tri_"))
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: COLMAP logs every step at INFO
    try:
        db = work / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        if shared:
            reader.camera_params = ",".join(f"{v:.9g}" for v in pinhole[views[0].name][2])
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.num_threads = num_threads
        extraction.sift.max_num_features = max_features
        extraction.sift.peak_threshold = peak_threshold
        pycolmap.extract_features(
            db,
            folder,
            image_names=[image_paths[c.name].name for c in views],
            camera_mode=pycolmap.CameraMode.SINGLE if shared else pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
        )
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = num_threads
        matching.guided_matching = guided_matching
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification)

        database = pycolmap.Database.open(db)
        try:
            db_images = database.read_all_images()
        finally:
            database.close()
        by_name = {c.name: c for c in views}
        rec = pycolmap.Reconstruction()
        for im in db_images:
            cam = by_name[Path(im.name).stem]
            w, h, params = pinhole[cam.name]
            if not rec.exists_camera(im.camera_id):
                rec.add_camera_with_trivial_rig(
                    pycolmap.Camera(
                        model="PINHOLE", width=w, height=h, params=params, camera_id=im.camera_id
                    )
                )
            pose = pycolmap.Rigid3d(
                pycolmap.Rotation3d(cam.rotation.double().numpy()),
                cam.translation.double().numpy(),
            )
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=im.name, camera_id=im.camera_id, image_id=im.image_id), pose
            )
        options = pycolmap.IncrementalPipelineOptions()
        options.triangulation.ignore_two_view_tracks = not two_view_tracks
        options.num_threads = num_threads
        options.random_seed = seed
        out = work / "model"
        out.mkdir()
        result = pycolmap.triangulate_points(rec, db, folder, out, options=options)
    finally:
        pycolmap.logging.minloglevel = level
        shutil.rmtree(work, ignore_errors=True)

    points = list(result.points3D.values())
    xyz = np.array([p.xyz for p in points], dtype=np.float64).reshape(-1, 3)
    rgb = np.array([p.color for p in points], dtype=np.float32).reshape(-1, 3) / 255.0
    summary = {
        "points": len(points),
        "mean_track_length": float(np.mean([p.track.length() for p in points])) if points else 0,
        "mean_reprojection_error_px": float(np.mean([p.error for p in points])) if points else 0,
        "views": len(views),
    }
    log.info("triangulated %s", summary)
    return xyz, rgb, summary


__all__ = ["triangulate_known_poses"]
