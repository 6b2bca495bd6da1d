"""`sagonline render SCENE --cameras C --view VIEW --out view.png`: one view to PNG or .npy."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from sagonline.apps.cli import CLICK_HELP
from sagonline.core.machine import BACKENDS, DEVICE_DEFAULT, DEVICE_HELP

OUT_SUFFIXES = (".png", ".jpg", ".jpeg", ".npy")
NO_CAMERAS = "none"  # --cameras none: an orbit around the scene, whatever camera file lies beside


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    rend = command_parser(sub, "render")
    rend.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    add_view_arguments(rend)
    rend.add_argument(
        "--view", default="0", help="an index in `sagonline cameras` (sorted by name) or a name"
    )
    rend.add_argument("--out", required=True, help="output .png/.jpg, or .npy (linear RGB)")
    rend.add_argument(
        "--overwrite", action="store_true", help="replace an earlier --out (a file, not an input)"
    )
    rend.add_argument(
        "--background",
        help="r,g,b in [0, 1]; default the colour the scene was fitted on (the fit_config.json "
        "beside it, as `segment` renders), else black",
    )
    rend.add_argument(
        "--backend",
        default="auto",
        choices=BACKENDS,
        help="auto: the compiled kernel on the CPU; on CUDA gsplat, else the Triton walk, else "
        "torch",
    )
    rend.set_defaults(func=cmd_render)


def add_view_arguments(parser) -> None:
    """--cameras, --orbit, --inside, --width/--height, --device, --drop-nonfinite: how every
    command that renders picks its views."""
    parser.add_argument(
        "--cameras",
        help="cameras.json, transforms.json, poses_bounds.npy, COLMAP folder or .npz; without "
        "it, the camera file beside the scene (its folder's, or a 3DGS output's cameras.json), "
        f"else an orbit around the scene's bounds; {NO_CAMERAS}: that orbit, whatever lies "
        "beside it",
    )
    parser.add_argument(
        "--orbit",
        type=int,
        default=0,
        metavar="N",
        help="N views on a ring around the scene (from the first camera, or around the "
        "scene's bounds without --cameras)",
    )
    parser.add_argument(
        "--inside",
        action="store_true",
        help="without --cameras: the views stand at the scene's centre and look out (a room or "
        "a scene captured from within), instead of an orbit around it",
    )
    parser.add_argument("--width", type=int, help="render width (cameras rescaled)")
    parser.add_argument("--height", type=int, help="render height")
    parser.add_argument("--device", default=DEVICE_DEFAULT, help=DEVICE_HELP)
    parser.add_argument(
        "--drop-nonfinite", action="store_true", help="drop Gaussians with NaN/Inf values"
    )
    parser.epilog = f"Views and clicks: {CLICK_HELP}."


def add_every_argument(parser, picks: str) -> None:
    """--every N (default None, read as 1: every view), for `segment` and `view`; `picks` says
    which views the command then works on."""
    parser.add_argument(
        "--every",
        type=int,
        metavar="N",
        help=f"{picks}; default 1, all: N times less of the segmenter's time, a sparser video "
        "for it; views keep their numbers and names",
    )


def find_cameras(args: argparse.Namespace, scene: Path) -> None:
    """Where the command line names no --cameras, set `args.cameras` to the camera file beside
    the scene file `scene` (`cameras_beside`: the views it was fitted or trained on), and
    `args.cameras_found` to whether it did; `--cameras none` or --inside: none (an orbit
    around the scene's bounds, or the turn from its centre)."""
    from sagonline.scene.io.cameras import cameras_beside

    args.cameras_found = False
    if args.cameras is not None and str(args.cameras).lower() == NO_CAMERAS:
        args.cameras = None
    elif args.cameras is None and not args.inside:
        args.cameras = cameras_beside(scene)
        args.cameras_found = args.cameras is not None


def recorded_path(path) -> str | None:
    """A path as a segment folder's labels.json records it: absolute, so that a figure or a
    replay run from another folder reads the same file (None stays None)."""
    return None if path is None else os.path.abspath(path)


def views_of(args: argparse.Namespace, scene, say: bool = False):
    """The views the view arguments (`add_view_arguments`, after `find_cameras`) pick for
    `scene`; `say`: where they are not simply the --cameras file's, a line saying which."""
    from sagonline.core.errors import CameraFileError
    from sagonline.scene.views import load_views

    found = args.cameras_found
    try:
        views = load_views(
            args.cameras,
            scene,
            orbit=args.orbit,
            width=args.width,
            height=args.height,
            inside=args.inside,
        )
    except CameraFileError as exc:
        if not found:
            raise
        raise CameraFileError(
            f"{exc} (found beside the scene, as no --cameras was given: --cameras {NO_CAMERAS} "
            "for an orbit around it, or --cameras naming its camera file)"
        ) from None
    if found:
        views.source += f" (found beside the scene; --cameras {NO_CAMERAS}: an orbit around it)"
    single = len(views.cameras) == 1 and not args.orbit
    if single:  # a vote from one side only: most Gaussians unseen
        views.source += "; one view only: --orbit N makes a ring of N views from it"
    if say and (args.cameras is None or args.orbit or found or single):
        print(f"views: {views.source}", file=sys.stderr)
    return views


def parse_background(text: str) -> list[float]:
    """'r,g,b' with each value in [0, 1]."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 3 or not all(0.0 <= v <= 1.0 for v in values):
        raise ValueError(f"--background {text!r}: give three values r,g,b in [0, 1]")
    return values


def warn_if_empty(alpha, index: int, cam) -> None:
    """Say so when a view shows (almost) nothing of the scene: an all-background image is
    otherwise written without a word (a camera of another scene, facing away, too close)."""
    import sys

    covered = float((alpha > 0.5).float().mean())
    if covered < 0.001:
        print(
            f"warning: view {index} ('{cam.name}') shows almost nothing of the scene ("
            f"{100 * covered:.2f}% of its pixels): is the camera of this scene, and facing it?",
            file=sys.stderr,
        )


def cmd_render(args: argparse.Namespace) -> int:

    from sagonline.core.files import atomic_write_image, atomic_write_npy
    from sagonline.core.machine import check_device
    from sagonline.core.outputs import OutputError, check_not_input
    from sagonline.render import render
    from sagonline.render.api import resolve_backend
    from sagonline.scene.io import fitted_background, read_scene, scene_file
    from sagonline.scene.io.cameras import camera_input_files
    from sagonline.scene.views import view_index

    scene = scene_file(args.scene)
    find_cameras(args, scene)
    out = Path(args.out)
    inputs = [scene, *(camera_input_files(args.cameras) if args.cameras else [])]
    check_not_input(out, inputs)
    if out.is_dir():
        raise OutputError(f"--out {out} is a folder; give a file path such as {out}/view.png")
    if out.suffix.lower() not in OUT_SUFFIXES:
        raise ValueError(f"--out {out}: use a .png, .jpg or .npy path (got {out.suffix!r})")
    if out.exists() and not args.overwrite:
        raise OutputError(f"--out {out} exists; pass --overwrite to replace it")
    background = (
        parse_background(args.background)
        if args.background is not None
        else list(fitted_background(scene) or (0.0, 0.0, 0.0))
    )
    args.device = check_device(args.device)
    resolve_backend(args.backend, args.device)
    g = read_scene(scene, drop_nonfinite=args.drop_nonfinite)
    views = views_of(args, g)
    index = view_index(args.view, views.cameras)
    cam = views.cameras[index]
    out_img = render(
        g.to(args.device),
        cam.to(args.device),
        background=background,
        backend=args.backend,
    )
    rgb = out_img.rgb.clamp_min(0).cpu().numpy().astype(np.float32)
    warn_if_empty(out_img.alpha, index, cam)
    if out.suffix.lower() == ".npy":
        atomic_write_npy(out, rgb)
    else:
        atomic_write_image(out, (rgb.clip(0, 1) * 255 + 0.5).astype(np.uint8))
    print(f"wrote {out} ({cam.width}x{cam.height}, view {index} '{cam.name}'; {views.source})")
    return 0
