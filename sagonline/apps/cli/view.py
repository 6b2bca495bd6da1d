"""`sagonline view SCENE`: the scene in the browser (viser), clicks as prompts, the labels
spreading through the splats view by view, and the exports of `sagonline segment`
(`sagonline.apps.viewer`)."""

from __future__ import annotations

import sys
import time

from sagonline.apps.cli.options import (
    add_min_weight_argument,
    add_segmenter_arguments,
    label_min_weight,
    segmenter_options,
)
from sagonline.apps.cli.render import (
    add_every_argument,
    add_view_arguments,
    find_cameras,
    recorded_path,
    views_of,
)
from sagonline.core.machine import BACKENDS


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    view = command_parser(sub, "view")
    view.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    add_view_arguments(view)
    add_every_argument(view, "show, render and segment every N-th view only (0, N, 2N, ...)")
    add_segmenter_arguments(view)
    view.add_argument("--backend", default="auto", choices=BACKENDS)
    add_min_weight_argument(view)
    view.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to serve on (default 127.0.0.1: this machine only; another address lets "
        "anyone who reaches it click and Export, which writes files here)",
    )
    view.add_argument("--port", type=port_number, default=8080, help="1-65535, free (8080)")
    view.add_argument("--out", help="the Export button's folder (default: segment-<scene>-<time>)")
    view.set_defaults(func=cmd_view)


def segmenter_builder(args):
    """kind -> that segmenter of the registry, with the command line's checkpoint and options
    (the checks of `sagonline segment`, for a click prompt)."""
    from argparse import Namespace

    from sagonline.apps.cli.options import build_segmenter
    from sagonline.segment.prompts import Prompt

    def build(kind: str, options: tuple[str, ...] = ()):
        given = [*args.segmenter_option, *options]
        return build_segmenter(
            Namespace(**{**vars(args), "segmenter": kind, "segmenter_option": given}), Prompt()
        )

    return build


def needs_embeddings(segmenter) -> bool:
    """Whether the segmenter prepares something per view (a model's embeddings)."""
    from sagonline.segment.base import VideoSegmenter

    return type(segmenter).prepare is not VideoSegmenter.prepare


def port_number(text: str) -> int:
    """--port: a TCP port in [1, 65535] (viser's server thread died on others and the command
    waited for it forever)."""
    import argparse

    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is not a port in [1, 65535]")
    return port


def check_port_free(host: str, port: int) -> None:
    """Refuse a port another program (another viewer) is serving on: viser would silently take
    the next one, and the printed address would not be the one asked for."""
    import socket

    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ValueError(
                f"--port {port}: cannot serve on {host}:{port} ({exc.strerror or exc}); another "
                "viewer may be running there: pass another --port"
            ) from None


def warn_if_exposed(host: str) -> None:
    """Say so when the viewer serves beyond this machine: Export writes files here."""
    import ipaddress

    try:
        local = ipaddress.ip_address(host).is_loopback
    except ValueError:
        local = host == "localhost"
    if not local:
        print(
            f"warning: serving on {host}: anyone who can reach this machine there can click "
            "and Export (which writes files here); --host 127.0.0.1 keeps it local",
            file=sys.stderr,
        )


def cmd_view(args) -> int:
    from sagonline.apps.viewer.app import ViewerApp
    from sagonline.apps.viewer.session import SegmentSession
    from sagonline.core.machine import check_device
    from sagonline.core.outputs import check_not_input
    from sagonline.core.plugins import SEGMENTERS
    from sagonline.render.api import resolve_backend
    from sagonline.scene.io import fitted_background, read_scene, scene_file
    from sagonline.scene.io.cameras import camera_input_files
    from sagonline.scene.views import check_every, check_trajectory, every_line, segmented_views

    scene = scene_file(args.scene)
    find_cameras(args, scene)
    every = check_every(args.every)  # refused before the scene is read
    stem = scene.parent.name if scene.name == "point_cloud.ply" else scene.stem
    out = args.out or f"segment-{stem}-{time.strftime('%Y%m%d-%H%M%S')}"
    check_not_input(out, [scene, *(camera_input_files(args.cameras) if args.cameras else [])])
    check_port_free(args.host, args.port)
    warn_if_exposed(args.host)
    args.device = check_device(args.device)
    resolve_backend(args.backend, args.device)
    min_weight = label_min_weight(args)
    g = read_scene(scene, drop_nonfinite=args.drop_nonfinite)
    views = views_of(args, g)
    cams = segmented_views(views.cameras, every)
    check_trajectory(cams)
    build = segmenter_builder(args)
    segmenter = build(args.segmenter)
    line = every_line(views.cameras, every, 0)
    print(f"views: {views.source}; rendering {line} ...", file=sys.stderr)
    session = SegmentSession(
        g,
        cams,
        segmenter=segmenter,
        segmenter_kind=args.segmenter,
        segmenter_options=segmenter_options(args),
        backend=args.backend,
        device=args.device,
        background=fitted_background(scene) or (0.0, 0.0, 0.0),
        min_weight=min_weight,
    )
    info = {
        "cameras": recorded_path(args.cameras),
        "views": views.source,
        "orbit": args.orbit,
        "inside": args.inside,
        "render_size": [args.width, args.height] if args.width else None,
        "every": every,
        "inbetween": 0,
    }
    app = ViewerApp(
        session,
        scene=scene.absolute(),  # labels.json records it so (`recorded_path`)
        info=info,
        host=args.host,
        port=args.port,
        out=out,
        make_segmenter=build,
        segmenters=tuple(SEGMENTERS.keys()),
    )
    print(
        f"viewer at {app.url} ({len(cams)} views rendered in "
        f"{session.render_seconds:.1f} s; segmenter {args.segmenter}"
        f"{', its embeddings are made in the background' if needs_embeddings(segmenter) else ''}"
        "); Ctrl+C stops it",
        flush=True,
    )
    try:
        while True:
            time.sleep(1.0)
    finally:
        session.stop()
        app.server.stop()
