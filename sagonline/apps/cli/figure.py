"""`sagonline figure SEGMENT_DIR --out x.png`: a picture of a `sagonline segment` folder.

For a few of its views (rows, each named in its first tile): the scene's render, the label
render, each object PLY rendered alone and, with one object, the scene without it (columns,
titled once at the top), on the colour the scene was fitted on as `segment` renders its frames
(the fit_config.json beside it; else black). The object PLYs are read back
like any scene file, so the picture shows what another 3DGS tool gets from them. The views are
the folder's own trajectory, rebuilt from its labels.json (cameras, orbit, in-between views,
render size).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sagonline.core.machine import BACKENDS

TITLE_PX = 22  # height of the title strip above the columns


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    fig = command_parser(sub, "figure")
    fig.add_argument("folder", help="a `sagonline segment` output folder")
    fig.add_argument(
        "--views", default="0", help="comma-separated view indices of the folder (default 0)"
    )
    fig.add_argument("--out", required=True, help="output .png or .jpg")
    fig.add_argument("--overwrite", action="store_true", help="replace an earlier --out")
    fig.add_argument("--backend", default="auto", choices=BACKENDS)
    fig.set_defaults(func=cmd_figure)


def folder_views(info: dict, scene) -> list:
    """The segment folder's trajectory, as its labels.json records it: its views (every
    `every`-th and the prompt's) and the views slerped in between."""
    from sagonline.scene.views import load_views, trajectory, view_index

    width, height = info["prompt"]["render_size"]
    views = load_views(
        info.get("cameras"),
        scene,
        orbit=info.get("orbit") or 0,
        width=width,
        height=height,
        inside=bool(info.get("inside")),
    )
    every = info.get("every") or 1
    keep = view_index(info["prompt"].get("view_name", "0"), views.cameras) if every > 1 else 0
    return trajectory(views.cameras, every=every, keep=keep, inbetween=info.get("inbetween") or 0)


def put_text(image: np.ndarray, text: str, org: tuple[int, int], height: int, color) -> None:
    """Write `text` into `image` (in place) at most `height` px tall and as wide as fits."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (w, h), _ = cv2.getTextSize(text, font, 1.0, 1)
    scale = min(height / max(h, 1), (image.shape[1] - org[0] - 2) / max(w, 1), 0.6)
    cv2.putText(image, text, org, font, max(scale, 0.2), color, 1, cv2.LINE_AA)


def header(widths: list[int], titles: list[str]) -> np.ndarray:
    """A white strip naming each column (the columns' widths in px)."""
    strips = []
    for width, title in zip(widths, titles, strict=True):
        strip = np.full((TITLE_PX, width, 3), 255, np.uint8)
        put_text(strip, title, (3, TITLE_PX - 7), TITLE_PX - 10, (0, 0, 0))
        strips.append(strip)
    return np.concatenate(strips, axis=1)


def read_folder_record(folder: Path) -> dict:
    """A segment folder's labels.json, with what a figure reads checked: the scene's path, the
    label names, the prompt's render size (a problem names the file and the field)."""
    from sagonline.core.errors import PromptError
    from sagonline.core.files import read_json_object

    path = folder / "labels.json"
    info = read_json_object(path, ValueError, "not readable JSON", "a labels.json (an object)")
    names = info.get("names")
    if not isinstance(info.get("scene"), str):
        raise PromptError(f"{path}: scene must name the scene file, found {info.get('scene')!r}")
    if not (isinstance(names, list) and names and all(isinstance(n, str) for n in names)):
        raise PromptError(f"{path}: names must be a list of label names, found {names!r}")
    size = (
        (info.get("prompt") or {}).get("render_size")
        if isinstance(info.get("prompt"), dict)
        else None
    )
    if not (
        isinstance(size, list)
        and len(size) == 2
        and all(isinstance(v, int) and v > 0 for v in size)
    ):
        raise PromptError(f"{path}: prompt.render_size must be [width, height], found {size!r}")
    every = info.get("every", 1)
    if not (isinstance(every, int) and not isinstance(every, bool) and every >= 1):
        raise PromptError(f"{path}: every must be a whole number of 1 or more, found {every!r}")
    if every > 1 and not isinstance(info["prompt"].get("view_name"), str):
        raise PromptError(f"{path}: prompt.view_name must name the prompt's view (every: {every})")
    return info


def check_same_scene(folder: Path, info: dict, scene) -> None:
    """The scene labels.json names must be the one the folder's labels were made on: the same
    file (its SHA-256, where recorded) and as many Gaussians as labels.npy holds."""
    import numpy as np

    from sagonline.core.provenance import digest_file

    recorded = (
        (info.get("inputs") or {}).get("scene") if isinstance(info.get("inputs"), dict) else None
    )
    if recorded and recorded != digest_file(info["scene"]):
        raise ValueError(
            f"{folder}/labels.json: its scene {info['scene']} is not the file the labels were "
            "made on (its SHA-256 differs)"
        )
    labels_file = folder / "labels.npy"
    if labels_file.is_file():
        count = len(np.load(labels_file, mmap_mode="r", allow_pickle=False))
        if count != len(scene):
            raise ValueError(
                f"{labels_file}: {count} labels, but the scene {info['scene']} has "
                f"{len(scene)} Gaussians: not this folder's scene"
            )


def cmd_figure(args) -> int:
    from sagonline.core.files import atomic_write_image
    from sagonline.core.outputs import OutputError, check_not_input
    from sagonline.labels.colours import label_colors
    from sagonline.render.api import render, to_uint8
    from sagonline.scene.io import fitted_background, read_scene
    from sagonline.scene.io.masks import read_mask

    folder, out = Path(args.folder), Path(args.out)
    if not (folder / "labels.json").is_file():
        raise ValueError(f"{folder}: no labels.json (not a `sagonline segment` output folder)")
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"--out {out}: a figure is a .png or .jpg file")
    info = read_folder_record(folder)
    if not Path(info["scene"]).exists():
        raise ValueError(
            f"{folder}/labels.json: its scene {info['scene']} is not here (a folder written "
            "before its paths were recorded absolute: run figure from the folder it was made in)"
        )
    check_not_input(
        out, [folder, info["scene"], *([info["cameras"]] if info.get("cameras") else [])]
    )
    if out.exists() and not args.overwrite:
        raise OutputError(f"--out {out} exists; pass --overwrite to replace it")
    scene = read_scene(info["scene"])
    check_same_scene(folder, info, scene)
    cams = folder_views(info, scene)
    try:
        picks = [int(v) for v in args.views.split(",")]
    except ValueError:
        raise ValueError(f"--views {args.views!r}: comma-separated view indices") from None
    bad = [v for v in picks if not 0 <= v < len(cams)]
    if bad:
        raise ValueError(f"--views: view {bad[0]} is out of range (the folder has {len(cams)})")
    objects = {p.stem: read_scene(p) for p in sorted((folder / "objects").glob("*.ply"))}
    rest = sorted(folder.glob("scene_without_*.ply"))
    colors = label_colors(len(info["names"]))
    titles = ["scene", "labels", *(f"{name} alone" for name in objects)]
    if len(objects) == 1 and rest:
        titles.append(f"without {next(iter(objects))}")
    bg = fitted_background(info["scene"]) or (0.0, 0.0, 0.0)  # as segment saw it
    ink = (0, 0, 0) if sum(bg) > 1.5 else (255, 255, 255)  # the view's name, legible

    def show(g, cam) -> np.ndarray:
        return to_uint8(render(g, cam, background=bg, backend=args.backend).rgb)

    rows = []
    for v in picks:
        cam = cams[v]
        label_png = next((folder / "views").glob(f"{v:04d}_*_labels.png"), None)
        if label_png is None:
            raise ValueError(f"{folder}/views: no label render of view {v}")
        labels = read_mask(
            label_png, "ids", max_labels=len(info["names"]), max_pixels=cam.width * cam.height
        ).labels
        if labels.shape != (cam.height, cam.width):
            raise ValueError(
                f"{label_png}: {labels.shape[1]}x{labels.shape[0]}, but view {v} renders at "
                f"{cam.width}x{cam.height}: not this folder's label render"
            )
        tiles = [show(scene, cam), colors[labels].astype(np.uint8)]
        tiles += [show(g, cam) for g in objects.values()]
        if len(titles) > len(tiles):
            tiles.append(show(read_scene(rest[0]), cam))
        put_text(tiles[0], f"view {v}", (3, 14), 10, ink)
        rows.append(np.concatenate(tiles, axis=1))
    widths = [tile.shape[1] for tile in tiles]
    atomic_write_image(out, np.concatenate([header(widths, titles), *rows], axis=0))
    print(f"wrote {out}: " + " | ".join(titles) + f"; views {args.views}")
    return 0
