"""A picture of a `sagonline segment` folder: for a few of its views, the scene's render, the
label render, and each object PLY rendered alone (then the scene without the objects).

    python bench/figure_segment.py SEGMENT_DIR --cameras CAMS [--views 0,8,16] --out docs/x.png

The object PLYs are read back like any scene file, so the picture shows what another 3DGS tool
gets from them. Views are the folder's trajectory (the cameras the segmentation rendered:
pass the same --cameras/--width/--height/--orbit as the segment command).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    from sagonline.cli.views import load_views
    from sagonline.io import read_scene
    from sagonline.recording import label_colors
    from sagonline.render.api import render, to_uint8
    from sagonline.trajectory import insert_between

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder")
    parser.add_argument("--cameras", required=True)
    parser.add_argument("--width", type=int)
    parser.add_argument("--height", type=int)
    parser.add_argument("--orbit", type=int, default=0)
    parser.add_argument("--inbetween", type=int, default=0)
    parser.add_argument("--views", default="0")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    folder = Path(args.folder)
    info = json.loads((folder / "labels.json").read_text())
    scene = read_scene(info["scene"])
    views = load_views(args.cameras, scene, orbit=args.orbit, width=args.width, height=args.height)
    cams = insert_between(views.cameras, args.inbetween)
    files = sorted((folder / "objects").glob("*.ply"))
    objects = [read_scene(p) for p in files]
    rest = sorted(folder.glob("scene_without_*.ply"))
    colors = label_colors(len(info["names"]))
    rows = []
    for v in (int(x) for x in args.views.split(",")):
        cam = cams[v]
        labels = np.array(Image.open(next((folder / "views").glob(f"{v:04d}_*_labels.png"))))
        tiles = [to_uint8(render(scene, cam, backend="auto").rgb), colors[labels].astype(np.uint8)]
        tiles += [to_uint8(render(g, cam, backend="auto").rgb) for g in objects]
        if len(objects) == 1 and rest:
            tiles.append(to_uint8(render(read_scene(rest[0]), cam, backend="auto").rgb))
        rows.append(np.concatenate(tiles, axis=1))
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out)
    print(f"wrote {args.out}: scene | label render | " + " | ".join(p.stem for p in files))


if __name__ == "__main__":
    main()
