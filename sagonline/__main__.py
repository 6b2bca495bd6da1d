"""Command line: `python -m sagonline info PLY`, `render PLY ...`, `segment PLY ...` and
`export RUN_DIR` (the last two: sagonline/segment_cli.py)."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

OUT_SUFFIXES = (".png", ".jpg", ".jpeg", ".npy")


def scene_file(path: str | Path) -> Path:
    """The scene file itself, or the point_cloud.ply inside a folder: the folder's own, its
    gaussians/ one, or the latest point_cloud/iteration_*/ one (a 3DGS output folder)."""
    from sagonline.io import SceneFileError

    path = Path(path)
    if not path.is_dir():
        return path
    for candidate in (path / "point_cloud.ply", path / "gaussians" / "point_cloud.ply"):
        if candidate.is_file():
            return candidate
    iterations = sorted(
        path.glob("point_cloud/iteration_*/point_cloud.ply"),
        key=lambda p: int("".join(filter(str.isdigit, p.parent.name)) or 0),
    )
    if iterations:
        return iterations[-1]
    raise SceneFileError(
        f"{path}: is a folder with no point_cloud.ply (looked in it, in gaussians/ and in "
        "point_cloud/iteration_*/); give the .ply or .splat file"
    )


def _cmd_info(args: argparse.Namespace) -> int:
    from sagonline.io import read_scene

    args.scene = scene_file(args.scene)
    g = read_scene(args.scene, drop_nonfinite=args.drop_nonfinite)
    lo, hi = g.bounding_box()
    fmt = "splat (32 bytes per splat)" if Path(args.scene).suffix == ".splat" else "ply"
    kind = "2DGS surfels" if g.kind == "2dgs" else "3DGS ellipsoids"
    print(f"file:        {args.scene}")
    print(f"format:      {fmt}, {kind}")
    print(f"gaussians:   {len(g)}")
    print(f"sh degree:   {g.sh_degree}")
    print(f"normals:     {'yes' if g.normals is not None else 'no'}")
    print(f"bbox min:    {' '.join(f'{v:.4g}' for v in lo.tolist())}")
    print(f"bbox max:    {' '.join(f'{v:.4g}' for v in hi.tolist())}")
    print(f"opacity:     mean {g.opacities.mean():.3f}, min {g.opacities.min():.3f}")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    import torch

    from sagonline.io import read_scene
    from sagonline.io.cameras import camera_input_files, load_cameras
    from sagonline.render import render
    from sagonline.utils import atomic_write_image, atomic_write_npy

    args.scene = scene_file(args.scene)
    out_path = Path(args.out)
    if out_path.suffix.lower() not in OUT_SUFFIXES:
        raise SystemExit(
            f"error: --out {out_path}: use a .png, .jpg or .npy path (got {out_path.suffix!r})"
        )
    refuse_inputs(out_path, [Path(args.scene), *camera_input_files(args.cameras)])
    if out_path.exists() and not args.overwrite:
        raise SystemExit(f"error: --out {out_path} exists; pass --overwrite to replace it")
    if (args.width is None) != (args.height is None):
        raise SystemExit("error: give both --width and --height, or neither")
    background = parse_background(args.background)
    g = read_scene(args.scene, drop_nonfinite=args.drop_nonfinite).to(args.device)
    cams = load_cameras(args.cameras)
    if not 0 <= args.view < len(cams):
        raise SystemExit(
            f"error: --view {args.view} is out of range: {args.cameras} has "
            f"{len(cams)} cameras (0..{len(cams) - 1})"
        )
    cam = cams[args.view]
    if args.width is not None:
        try:
            cam = cam.scaled(args.width, args.height)
        except ValueError as exc:
            raise SystemExit(f"error: --width {args.width} --height {args.height}: {exc}") from None
    bg = torch.tensor(background)
    out = render(g, cam, background=bg, backend=args.backend)
    rgb = out.rgb.clamp_min(0).cpu().numpy().astype(np.float32)
    if out_path.suffix.lower() == ".npy":
        atomic_write_npy(out_path, rgb)
    else:
        atomic_write_image(out_path, (rgb.clip(0, 1) * 255 + 0.5).astype(np.uint8))
    print(f"wrote {out_path} ({cam.width}x{cam.height}, view {args.view} '{cam.name}')")
    return 0


def refuse_inputs(out: Path, inputs: list[Path]) -> None:
    """Stop when `out` is (or resolves to, or is a hard link of) any input file."""
    target = out.resolve()
    for path in inputs:
        same = path.resolve() == target
        if not same and out.exists() and path.exists():
            same = os.path.samefile(out, path)
        if same:
            raise SystemExit(
                f"error: --out {out} is one of the inputs ({path}); choose another path"
            )


def parse_background(text: str) -> list[float]:
    """'r,g,b' with each value in [0, 1]."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise SystemExit(f"error: --background {text!r}: give three values r,g,b in [0, 1]")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="sagonline", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    info = sub.add_parser("info", help="format, Gaussian count, SH degree, bounding box")
    info.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    info.add_argument("--drop-nonfinite", action="store_true", help="drop NaN/Inf rows")
    info.set_defaults(func=_cmd_info)
    rend = sub.add_parser("render", help="render one camera to PNG or .npy (float32 HxWx3)")
    rend.add_argument("scene")
    rend.add_argument(
        "--cameras",
        required=True,
        help="cameras.json, transforms.json, poses_bounds.npy, COLMAP folder, .npz",
    )
    rend.add_argument("--view", type=int, default=0)
    rend.add_argument("--width", type=int)
    rend.add_argument("--height", type=int)
    rend.add_argument("--out", required=True, help="output .png/.jpg, or .npy (linear RGB)")
    rend.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    rend.add_argument("--background", default="0,0,0", help="r,g,b in [0, 1]")
    rend.add_argument("--backend", default="torch", choices=["torch", "native", "gsplat", "auto"])
    rend.add_argument("--device", default="cpu")
    rend.add_argument("--drop-nonfinite", action="store_true")
    rend.set_defaults(func=_cmd_render)
    from sagonline.segment_cli import add_parsers

    add_parsers(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from sagonline.io import SceneFileError
    from sagonline.io.cameras import CameraFileError

    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (SceneFileError, CameraFileError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
