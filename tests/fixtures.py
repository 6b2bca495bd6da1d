"""Shared test helpers: tiny random scenes and cameras, on-disk replicas of dataset layouts,
composed configs, and the path to the shared real data. conftest.py turns some into fixtures."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from sagonline.scene.cameras import Camera, intrinsics, look_at, make_camera
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.generator import make_scene
from sagonline.scene.io import write_ply

ROOT = Path(__file__).resolve().parents[1]  # the repository
CONF = str(ROOT / "conf")
TINY = [
    f"dataset.adapter.{s}.{k}={v}"
    for s in ("forward_single", "cluttered_360")
    for k, v in (
        ("width", 64),
        ("height", 48),
        ("num_gaussians", 4000),
        ("num_train_views", 8),
        ("num_eval_views", 3),
    )
]


def compose_config(name: str, *overrides: str, typed: bool = True):
    """conf/<name>.yaml composed with `overrides`: the typed EvalConfig / ScenesConfig the entry
    point would run with, or (typed=False) the DictConfig Hydra composed."""
    from hydra import compose, initialize_config_dir

    from bench.runners.config import EvalConfig, ScenesConfig, register_schemas, to_config

    register_schemas()
    if name == "eval":  # each test run caches in its own folder unless it says otherwise
        overrides = ("cache_dir=null", *overrides)
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(name, overrides=list(overrides))
    if not typed:
        return cfg
    return to_config(cfg, EvalConfig if name == "eval" else ScenesConfig)


def cfg_with(*overrides: str):
    """The eval config on the tiny synthetic presets, progress bars off."""
    return compose_config("eval", *TINY, "progress=false", *overrides)


DATA = ROOT.parent / "shared" / "data"


def shared_data(*parts: str) -> Path:
    path = DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"real data not found at {path} (the shared data folder sits beside the repo)")
    return path


def random_gaussians(
    n: int, kind: str = "3dgs", seed: int = 0, sh_degree: int = 1, spread: float = 1.0
) -> Gaussians:
    """n random Gaussians around the origin, sized to cover a few pixels of `small_camera`."""
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    k = (sh_degree + 1) ** 2
    dims = 3 if kind == "3dgs" else 2
    return Gaussians(
        means=torch.tensor(rng.uniform(-spread, spread, (n, 3)), dtype=torch.float32),
        quats=torch.tensor(q, dtype=torch.float32),
        scales=torch.tensor(rng.uniform(0.05, 0.35, (n, dims)), dtype=torch.float32),
        opacities=torch.tensor(rng.uniform(0.2, 0.98, n), dtype=torch.float32),
        sh=torch.tensor(rng.normal(scale=0.6, size=(n, k, 3)), dtype=torch.float32),
    )


def small_camera(width: int = 26, height: int = 19, eye=(0.3, -4.0, 0.8), name: str = "cam"):
    K = intrinsics(width * 1.1, width * 1.1, width / 2 + 0.3, height / 2 - 0.2)
    return make_camera(K, look_at(eye, (0, 0, 0)), width, height, name)


def orbit_cameras(n: int, width: int = 32, height: int = 24) -> list[Camera]:
    K = intrinsics(width * 1.2, width * 1.2, width / 2, height / 2)
    return [
        make_camera(
            K, look_at([3 * np.cos(a), 3 * np.sin(a), 1.5], [0, 0, 0.3]), width, height, f"v{i}"
        )
        for i, a in enumerate(np.linspace(0, 2 * np.pi, n, False))
    ]


def write_poses_bounds(path: Path, cams: list[Camera]) -> None:
    """Inverse of `load_llff`: (N, 17) rows of [down, right, back, t | h, w, f] + bounds."""
    rows = []
    for c in cams:
        c2w = torch.linalg.inv(c.world_to_cam.double()).numpy()
        m = np.stack(
            [
                c2w[:3, 1],
                c2w[:3, 0],
                -c2w[:3, 2],
                c2w[:3, 3],
                [c.height, c.width, float(c.K[0, 0])],
            ],
            axis=1,
        )
        rows.append(np.concatenate([m.ravel(), [0.5, 10.0]]))
    np.save(path, np.array(rows))


def write_image(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), array)


def llff_scene(
    root: Path, names: list[str], width=32, height=24, image_dir="images_4", with_scene=True, seed=0
) -> tuple[list[Camera], object]:
    """An LLFF scene folder whose views are a tiny synthetic scene; returns cameras + scene."""
    scene = make_scene(
        layout="forward",
        num_gaussians=2500,
        width=width,
        height=height,
        num_train_views=len(names),
        num_eval_views=1,
        seed=seed,
    )
    cams = [
        make_camera(c.K, c.world_to_cam, width, height, n)
        for c, n in zip(scene.train_cameras, names, strict=True)
    ]
    root.mkdir(parents=True, exist_ok=True)
    write_poses_bounds(root / "poses_bounds.npy", cams)
    for n in names:
        write_image(root / image_dir / f"{n}.JPG", np.full((height, width, 3), 90, np.uint8))
    if with_scene:
        write_ply(root / "gaussians" / "point_cloud.ply", scene.gaussians)
    return cams, scene


def object_mask(scene, cam) -> np.ndarray:
    from sagonline.datasets.synthetic import gt_mask

    return gt_mask(scene, cam, scene.instance, scene.num_instances)


def write_colmap_text(folder: Path, cams: list[Camera], scale: float = 1.0) -> None:
    """A COLMAP text model (PINHOLE, one camera per view) of `cams`, `scale` times their size."""
    from scipy.spatial.transform import Rotation

    folder.mkdir(parents=True, exist_ok=True)
    cam_lines, image_lines = [], []
    for i, c in enumerate(cams, start=1):
        K = c.K.double().numpy() * scale
        w, h = round(c.width * scale), round(c.height * scale)
        cam_lines.append(f"{i} PINHOLE {w} {h} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}")
        w2c = c.world_to_cam.double().numpy()
        x, y, z, qw = Rotation.from_matrix(w2c[:3, :3]).as_quat()
        t = w2c[:3, 3]
        image_lines.append(f"{i} {qw} {x} {y} {z} {t[0]} {t[1]} {t[2]} {i} {c.name}.JPG\n")
    (folder / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (folder / "images.txt").write_text("\n".join(image_lines) + "\n")
    (folder / "points3D.txt").write_text("")


def write_nerf_transforms(path: Path, cams: list[Camera], names: list[str] | None = None) -> Path:
    """A NeRF `transforms.json` of `cams` (OpenGL camera-to-world), frames named by `names`."""
    import json

    frames = []
    for cam, name in zip(cams, names or [c.name for c in cams], strict=True):
        c2w = torch.linalg.inv(cam.world_to_cam.double()).numpy()
        c2w[:3, 1:3] *= -1.0  # OpenCV -> OpenGL axes
        frames.append({"file_path": f"./images/{name}", "transform_matrix": c2w.tolist()})
    meta = {
        "fl_x": float(cams[0].K[0, 0]),
        "fl_y": float(cams[0].K[1, 1]),
        "cx": float(cams[0].K[0, 2]),
        "cy": float(cams[0].K[1, 2]),
        "w": cams[0].width,
        "h": cams[0].height,
        "frames": frames,
    }
    path.write_text(json.dumps(meta))
    return path


def own_scene(folder: Path, views: int = 8, width: int = 48, height: int = 36, seed: int = 0):
    """A user's scene folder: point_cloud.ply, transforms.json (frames r_0 .. r_<views-1>, listed
    in file order) and a notes.txt; returns (folder, scene, cameras in name order, the first
    camera's ground-truth mask)."""
    from sagonline.datasets.synthetic import gt_mask

    scene = make_scene(
        layout="forward",
        num_gaussians=2000,
        width=width,
        height=height,
        num_train_views=views,
        num_eval_views=1,
        seed=seed,
    )
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "point_cloud.ply", scene.gaussians)
    names = [f"r_{i}" for i in range(views)]
    write_nerf_transforms(folder / "transforms.json", scene.train_cameras, names)
    (folder / "notes.txt").write_text("my notes\n")
    from sagonline.scene.io.cameras import load_cameras

    cams = load_cameras(folder / "transforms.json")
    return folder, scene, cams, gt_mask(scene, cams[0], scene.instance, scene.num_instances)


def tree_digest(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file below `folder` (what a command may not change)."""
    import hashlib

    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }
