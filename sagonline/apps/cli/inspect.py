"""`sagonline info SCENE`, `sagonline cameras CAMERAS` and `sagonline plugins`."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    info = command_parser(sub, "info")
    info.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    info.add_argument("--drop-nonfinite", action="store_true", help="drop NaN/Inf rows")
    info.set_defaults(func=cmd_info)
    cams = command_parser(sub, "cameras")
    cams.add_argument(
        "cameras",
        help="cameras.json, transforms.json, poses_bounds.npy, COLMAP folder, .npz; or a "
        "scene file (.ply, .splat): the camera file beside it, as render, segment and view read",
    )
    cams.set_defaults(func=cmd_cameras)
    plugins = command_parser(sub, "plugins")
    plugins.add_argument(
        "kind", nargs="?", choices=["segmenters", "datasets", "vote-rules"], default=None
    )
    plugins.add_argument("--keys", action="store_true", help="keys only, comma-separated")
    plugins.set_defaults(func=cmd_plugins)


def cmd_info(args: argparse.Namespace) -> int:
    from sagonline.scene.io import read_scene, scene_file

    path = scene_file(args.scene)
    g = read_scene(path, drop_nonfinite=args.drop_nonfinite)
    lo, hi = g.bounding_box()
    fmt = "splat (32 bytes per splat)" if Path(path).suffix == ".splat" else "ply"
    kind = "2DGS surfels" if g.kind == "2dgs" else "3DGS ellipsoids"
    print(f"file:        {path}")
    print(f"format:      {fmt}, {kind}")
    print(f"gaussians:   {len(g)}")
    print(f"sh degree:   {g.sh_degree}")
    print(f"normals:     {'yes' if g.normals is not None else 'no'}")
    print(f"bbox min:    {' '.join(f'{v:.4g}' for v in lo.tolist())}")
    print(f"bbox max:    {' '.join(f'{v:.4g}' for v in hi.tolist())}")
    print(f"opacity:     mean {g.opacities.mean():.3f}, min {g.opacities.min():.3f}")
    return 0


def scene_cameras(path: Path) -> Path:
    """`path`, or for a scene file (.ply, .splat) the camera file beside it (`cameras_beside`);
    CameraFileError for a scene file without one."""
    from sagonline.scene.io.cameras import CameraFileError, cameras_beside

    if path.suffix.lower() not in (".ply", ".splat"):
        return path
    found = cameras_beside(path)
    if found is None:
        raise CameraFileError(
            f"{path}: a scene file, and no camera file lies beside it (in its folder, or two "
            "up from a 3DGS output's point_cloud/iteration_<N>/): give its cameras.json, "
            "transforms.json, poses_bounds.npy or COLMAP folder"
        )
    return found


def cmd_cameras(args: argparse.Namespace) -> int:
    from sagonline.scene.views import load_views

    views = load_views(scene_cameras(Path(args.cameras)))
    print(f"# {views.source}: VIEW in render --view, segment --click VIEW:X,Y, --preview VIEW")
    print(f"{'index':>5}  {'name':<32} size")
    for i, cam in enumerate(views.cameras):
        print(f"{i:>5}  {cam.name:<32} {cam.width}x{cam.height}")
    print(
        f"# this numbering holds without --orbit; with --orbit N, render, segment and view "
        f"number a ring of N views instead (orbit_000.., starting at index 0's camera "
        f"'{views.cameras[0].name}'), at their --width/--height"
    )
    return 0


def cmd_plugins(args: argparse.Namespace) -> int:
    from sagonline.core.plugins import DATASETS, SEGMENTERS, VOTE_RULES

    registries = {"segmenters": SEGMENTERS, "datasets": DATASETS, "vote-rules": VOTE_RULES}
    chosen = [args.kind] if args.kind else list(registries)
    for kind in chosen:
        registry = registries[kind]
        if args.keys:
            print(",".join(registry.keys()))
            continue
        print(f"{kind}:")
        for plugin in registry:
            where = plugin.config.__name__
            if kind == "vote-rules":
                names = [f"consensus.{f.name}" for f in dataclasses.fields(plugin.config)]
                where = f"{where}: {', '.join(names) or 'no settings'}"
            print(f"  {plugin.key:<14} {plugin.summary} ({where})")
    return 0
