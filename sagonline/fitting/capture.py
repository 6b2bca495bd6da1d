"""What a fit takes from a capture on disk: its images at the fitting resolution, start points
(the capture's COLMAP points, else SIFT matches triangulated with the training cameras fixed,
cached beside the scene), and the nearest depth it records (for the camera clearance)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from sagonline.core import store
from sagonline.core.errors import DatasetError
from sagonline.fitting.config import FitConfig
from sagonline.fitting.start_points import split_views
from sagonline.fitting.triangulate import triangulate_known_poses
from sagonline.scene.io.cameras import read_colmap_points, read_poses_bounds
from sagonline.scene.io.images import read_rgb


def load_images(cams, images: dict[str, Path], max_side: int):
    """Cameras that have an image, rescaled so the longer side is at most `max_side`, and
    their images as (H, W, 3) float tensors in [0, 1]."""
    out_cams, out_imgs = [], []
    for cam in cams:
        if cam.name not in images:
            continue
        im = Image.fromarray(read_rgb(images[cam.name]))  # whole files only, size checked
        scale = min(1.0, max_side / max(im.size))
        w, h = max(1, round(im.size[0] * scale)), max(1, round(im.size[1] * scale))
        arr = np.asarray(im.resize((w, h), Image.Resampling.LANCZOS), np.float32) / 255.0
        out_cams.append(cam.scaled(w, h))
        out_imgs.append(torch.from_numpy(arr))
    return out_cams, out_imgs


WHITE = 0.9
"""A photograph's border is white when its median colour reaches this in every channel."""


def white_backdrop(
    images: list[torch.Tensor],  # each [H, W, 3] in [0, 1]
    share: float = 0.9,
    frame: float = 0.05,
) -> bool:
    """True when at least `share` of the photographs have a white border:
    the median colour of their outer `frame` (a fraction of each side) is >= WHITE in every
    channel. A studio sweep or turntable is; a room is not (mold_cape, mother_child, duck_queen:
    none of their photographs; mary_rose: all 35)."""
    if not images:
        return False
    white = 0
    for im in images:
        h, w = im.shape[:2]
        dy, dx = max(1, round(frame * h)), max(1, round(frame * w))
        border = torch.cat(
            [
                im[:dy].reshape(-1, 3),
                im[-dy:].reshape(-1, 3),
                im[:, :dx].reshape(-1, 3),
                im[:, -dx:].reshape(-1, 3),
            ]
        )
        white += bool((border.median(0).values >= WHITE).all())
    return white >= share * len(images)


def fitting_background(
    cfg: FitConfig,
    images: list[torch.Tensor],  # each [H, W, 3] in [0, 1]
) -> tuple[float, float, float]:
    """The colour the fit renders on: `cfg.background`, or white with `backdrop=detect` where
    the photographs show a white backdrop (`white_backdrop`)."""
    if cfg.backdrop == "detect" and white_backdrop(images):
        return (1.0, 1.0, 1.0)
    return tuple(cfg.background)


def resolve_background(
    cfg: FitConfig,
    images: list[torch.Tensor],  # each [H, W, 3] in [0, 1]
) -> None:
    """Set `cfg.background` to the colour the fit renders on (`fitting_background`); on a
    detected backdrop, also `random_background` off (the photographs show its colour)."""
    colour = fitting_background(cfg, images)
    if colour != tuple(cfg.background):
        cfg.random_background = False
    cfg.background = colour


def training_background(cfg: FitConfig, step: int) -> torch.Tensor | None:  # [3]
    """The colour training step `step` renders on with `random_background`, drawn from the
    seed and the step (a resumed fit draws the same); None without it (the fit's own)."""
    if not cfg.random_background:
        return None
    return torch.tensor(np.random.default_rng([cfg.seed, step]).random(3), dtype=torch.float32)


def detector_key(cfg: FitConfig) -> str:
    """What the triangulated start points depend on beside the views and the seed, for their
    cache's key ('' at the defaults, so the points cached before these settings stay valid)."""
    default = FitConfig()
    if (cfg.sift_peak_threshold, cfg.guided_matching) == (
        default.sift_peak_threshold,
        default.guided_matching,
    ):
        return ""
    return f"|peak={cfg.sift_peak_threshold:g}|guided={cfg.guided_matching}"


def initial_points(
    cfg: FitConfig,
    scene_dir: Path,
    cams,
    images: dict[str, Path],
    out: Path,
    shared: Sequence[Path] = (),
):
    """Start points for the fit and what they are: the capture's COLMAP points, else SIFT
    matches triangulated with the training cameras fixed (cached in `out`; also read from
    the folders in `shared`, the capture's other fits: a fit of the same training views, seed
    and detector settings, of any recipe, triangulated the same points), else None (random
    points in the frusta). Returns ((xyz, rgb) or None, description)."""
    if cfg.init not in ("auto", "colmap", "triangulate", "random"):
        raise DatasetError(f"fit.init={cfg.init!r}: use auto, colmap, triangulate or random")
    if cfg.init in ("auto", "colmap"):
        for sparse in (scene_dir / "sparse" / "0", scene_dir / "sparse"):
            if (sparse / "points3D.bin").is_file() or (sparse / "points3D.txt").is_file():
                xyz, rgb = read_colmap_points(sparse)
                return (xyz, rgb.astype(np.float32) / 255.0), f"colmap points ({len(xyz)})"
        if cfg.init == "colmap":
            raise DatasetError(f"{scene_dir}: fit.init=colmap but there is no sparse/ model")
    if cfg.init in ("auto", "triangulate"):
        train_idx, _ = split_views(cams, cfg.holdout_every, cfg.train_every)  # the fit's own
        train = [cams[i] for i in train_idx]
        cache = out / "init_points.store"
        key = ",".join(c.name for c in train) + f"|seed={cfg.seed}" + detector_key(cfg)
        for folder in [out, *shared]:
            path = folder / "init_points.store"
            cached = store.load_or_discard(path, "triangulated start points")
            if cached is not None and cached["views"] == key:
                xyz = cached["xyz"]
                return (xyz, cached["rgb"]), f"triangulated ({len(xyz)}, cached in {folder.name})"
        try:
            xyz, rgb, summary = triangulate_known_poses(
                train,
                images,
                seed=cfg.seed,
                peak_threshold=cfg.sift_peak_threshold,
                guided_matching=cfg.guided_matching,
            )
        except ImportError as exc:  # a machine without pycolmap (a GPU machine without a registry)
            why = (
                f"triangulation needs pycolmap ({exc}); install it (`pip install pycolmap`), or "
                f"put the start points a fit of seed {cfg.seed} cached beside this one at "
                f"{cache} (`make gpu-bundle` carries duck_queen's)"
            )
            if cfg.init == "triangulate":
                raise DatasetError(f"{scene_dir}: {why}") from exc
            print(f"note: {scene_dir}: {why}; random start points")
            return None, "random in frusta (no pycolmap)"
        except (ValueError, RuntimeError) as exc:  # e.g. images in several folders
            if cfg.init == "triangulate":
                raise DatasetError(f"{scene_dir}: triangulation failed: {exc}") from exc
            print(f"note: {scene_dir}: triangulation failed ({exc}); random start points")
            return None, "random in frusta"
        if len(xyz) >= 100:
            out.mkdir(parents=True, exist_ok=True)
            store.save(cache, {"xyz": xyz, "rgb": rgb, "views": key})
            return (xyz, rgb), (
                f"triangulated ({summary['points']} points, track "
                f"{summary['mean_track_length']:.2f}, error "
                f"{summary['mean_reprojection_error_px']:.2f} px)"
            )
        if cfg.init == "triangulate":
            raise DatasetError(f"{scene_dir}: only {len(xyz)} points triangulated")
    return None, "random in frusta"


def near_depth(cams, points, bounds) -> float:
    """The nearest scene depth the capture records: LLFF's near bound, else the 2nd percentile
    of the start points' depths over the training views, else 0 (unknown)."""
    if bounds is not None:
        return bounds[0]
    if points is None:
        return 0.0
    xyz = torch.tensor(points[0], dtype=torch.float32)
    depths = [cam.project(xyz)[1] for cam in cams]
    z = torch.cat([d[d > 0] for d in depths])
    return float(torch.quantile(z, 0.02)) if z.numel() else 0.0


def view_near_depths(scene_dir: Path, cams, points, quantile: float = 0.02) -> dict[str, float]:
    """Per view name, the nearest depth the capture records for that view: the smaller of the
    LLFF near bound of the `poses_bounds.npy` row whose camera centre is the view's and the
    `quantile` (`FitConfig.view_near_quantile`) of the depths of the start points (the
    capture's own points) inside its image;
    views with neither are left out. An LLFF bound is computed from some point set of its own
    and may lie beyond a small object in front of the background (mother_child's IMG_0977:
    near 4.65, the statuette at 3.7): the view clearance, which prunes whatever stands nearer
    than a fraction of this depth, must never prune what the capture's points show."""
    near: dict[str, float] = {}
    pb = Path(scene_dir) / "poses_bounds.npy"
    if pb.is_file():
        rows = read_poses_bounds(pb)
        centres = torch.from_numpy(rows[:, :15].reshape(-1, 3, 5)[:, :, 3]).float()
        scale = float((centres - centres.mean(0)).norm(dim=1).max()) or 1.0
        for cam in cams:
            dist = (centres - cam.center.cpu().float()).norm(dim=1)
            row = int(dist.argmin())
            if float(dist[row]) <= 1e-4 * scale:
                near[cam.name] = float(rows[row, 15])
    if points is not None:
        xyz = torch.tensor(points[0], dtype=torch.float32)
        for cam in cams:
            inside, z = cam.in_frame(xyz)
            if int(inside.sum()) >= 20:
                seen = float(torch.quantile(z[inside], quantile))
                near[cam.name] = min(near.get(cam.name, seen), seen)
    return near


def fit_near_depths(
    scene_dir: Path, cams, points, photographed, quantile: float
) -> dict[str, float]:
    """`view_near_depths` for a fit: the views with a photograph (names in `photographed`)
    with their points' `quantile` (`FitConfig.view_near_quantile`, the view clearance's), the
    pose-only views with the 2nd percentile (the pose-view clearance's, chosen with it)."""
    photos = [c for c in cams if c.name in photographed]
    return view_near_depths(scene_dir, cams, points) | view_near_depths(
        scene_dir, photos, points, quantile
    )
