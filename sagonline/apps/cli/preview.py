"""`sagonline segment --preview VIEW|all`: a view at its render size with a pixel grid to pick
clicks on, or every view small in one image (a contact sheet) to choose the view."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_preview(g, cams, view: str, out: Path, args, background=(0.0, 0.0, 0.0)) -> int:
    """VIEW at its render size with a light pixel grid (every 50 px, labelled every 100); `all`:
    the contact sheet of every view. Rendered on `background`, as the segmenter's frames are
    (the scene's fitted colour)."""
    import cv2

    from sagonline.scene.views import view_index

    if view == "all":
        return write_contact_sheet(g, cams, out, args, background)
    index = view_index(view, cams)
    from sagonline.core.files import atomic_write_image
    from sagonline.render.api import render, to_uint8

    if out.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"--out {out}: a preview is a .png or .jpg file")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out {out} exists; pass --overwrite to replace it")
    cam = cams[index]
    shown = render(
        g.to(args.device), cam.to(args.device), background=background, backend=args.backend
    )
    rgb = to_uint8(shown.rgb)
    image = np.ascontiguousarray(rgb)
    grid = image.copy()
    for x in range(0, cam.width, 50):
        cv2.line(grid, (x, 0), (x, cam.height - 1), (255, 255, 255), 1)
    for y in range(0, cam.height, 50):
        cv2.line(grid, (0, y), (cam.width - 1, y), (255, 255, 255), 1)
    image = cv2.addWeighted(image, 0.7, grid, 0.3, 0)
    for x in range(0, cam.width, 100):
        for y in range(0, cam.height, 100):
            cv2.putText(
                image,
                f"{x},{y}",
                (x + 2, y + 11),
                cv2.FONT_HERSHEY_PLAIN,
                0.8,
                (255, 255, 0),
                1,
                cv2.LINE_AA,
            )
    atomic_write_image(out, image)
    print(
        f"wrote {out}: view {index} '{cam.name}' at {cam.width}x{cam.height} (its render size: "
        f"click with --click {index}:X,Y in these pixels)"
    )
    return 0


def write_contact_sheet(g, cams, out: Path, args, background=(0.0, 0.0, 0.0)) -> int:
    """Every view in one image, each small and labelled with its index and name, to choose the
    view to click on (`--preview all`)."""
    import cv2

    from sagonline.core.files import atomic_write_image
    from sagonline.render.api import render, to_uint8

    if out.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"--out {out}: a preview is a .png or .jpg file")
    if out.exists() and not args.overwrite:
        raise ValueError(f"--out {out} exists; pass --overwrite to replace it")
    side = 200  # each tile's longer side
    renders = []
    for cam in cams:
        s = side / max(cam.width, cam.height)
        small = cam.scaled(max(1, round(cam.width * s)), max(1, round(cam.height * s)))
        out_ = render(
            g.to(args.device), small.to(args.device), background=background, backend=args.backend
        )
        renders.append(np.ascontiguousarray(to_uint8(out_.rgb)))
    height = max(r.shape[0] for r in renders)
    tiles = []
    for i, (cam, rgb) in enumerate(zip(cams, renders, strict=True)):
        tile = np.zeros((height + 16, side, 3), np.uint8)
        tile[16 : 16 + rgb.shape[0], : rgb.shape[1]] = rgb
        label = f"{i}: {cam.name}"[:28]
        cv2.putText(
            tile, label, (2, 12), cv2.FONT_HERSHEY_PLAIN, 0.9, (255, 255, 0), 1, cv2.LINE_AA
        )
        tiles.append(tile)
    columns = min(6, len(tiles))
    tiles += [np.zeros_like(tiles[0])] * (-len(tiles) % columns)
    rows = [np.concatenate(tiles[r : r + columns], 1) for r in range(0, len(tiles), columns)]
    atomic_write_image(out, np.concatenate(rows, 0))
    print(
        f"wrote {out}: all {len(cams)} views (index: name); preview one at its render size "
        "with --preview VIEW"
    )
    return 0
