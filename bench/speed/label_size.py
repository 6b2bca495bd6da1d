"""The scored label render's cost at the render's size and at the ground truth's
(`label_render.size`), in one process: ms per view and the ratio to the first size.

    python -m bench.speed.label_size [--scene PLY] [--cameras DIR] [--sizes 228x171,1296x972]
                                     [--views 10] [--repeats 3] [--out reports/bench_label_size.csv]

Defaults: duck_queen's seed-0 fit (`make scenes DATASET=duck_queen`) with its LLFF cameras from
../shared/data, at the captures' render size (228x171) and their masks' (1296x972); 2 labels,
min_weight 0.5, the label walk the eval resolves on the device. Each view is rendered once to
warm up, then `--repeats` times; a size's figure is the median over views of each view's median.
--quick: a generated 2k-surfel scene at 48x36 and 96x72, 2 views, one repeat (what the tests run).
"""

from __future__ import annotations

import argparse
import statistics
from functools import partial
from pathlib import Path

import pandas as pd
import torch

from bench import OUT_HELP, REPORTS, ROOT
from bench.speed.render import timed
from sagonline.core.files import atomic_write_text
from sagonline.core.machine import describe_device
from sagonline.render import render_labels
from sagonline.render.backends import resolve_vote_backend
from sagonline.scene.generator import make_scene
from sagonline.scene.io import read_scene
from sagonline.scene.views import load_views

DUCK = ROOT / "scenes" / "duck_queen" / "duck_queen" / "gaussians" / "point_cloud.ply"
DUCK_CAMERAS = ROOT.parent / "shared" / "data" / "duck_queen"


def scene_and_cameras(args):
    """(name, Gaussians, cameras): the scene file with its cameras, or (--quick) a generated one."""
    if args.quick:
        s = make_scene(layout="forward", num_gaussians=2_000, width=48, height=36)
        return "synthetic (2DGS, 2,000)", s.gaussians, s.train_cameras
    for path in (Path(args.scene), Path(args.cameras)):
        if not path.exists():
            raise SystemExit(f"error: {path} not found (fit it: make scenes DATASET=duck_queen)")
    g = read_scene(args.scene)
    folder = Path(args.scene).parent
    return f"{folder.parent.name}/{folder.name}", g, load_views(args.cameras, g).cameras


def sizes(text: str) -> list[tuple[int, int]]:
    try:
        return [tuple(int(v) for v in s.lower().split("x")) for s in text.split(",")]
    except ValueError:
        raise SystemExit(
            f"error: --sizes {text!r}: comma-separated WxH, say 228x171,1296x972"
        ) from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=str(DUCK))
    ap.add_argument("--cameras", default=str(DUCK_CAMERAS))
    ap.add_argument("--sizes", default="228x171,1296x972")
    ap.add_argument("--views", type=int, default=10, help="evenly spaced views timed")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(REPORTS / "bench_label_size.csv"), help=OUT_HELP)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    if args.quick:
        args.sizes, args.views, args.repeats = "48x36,96x72", 2, 1
    name, g, cams = scene_and_cameras(args)
    g = g.to(args.device)
    cams = [c.to(args.device) for c in cams[:: max(1, len(cams) // args.views)][: args.views]]
    labels = torch.arange(len(g), device=g.device) % 2
    backend = resolve_vote_backend("auto", g.device)
    wanted, rows = sizes(args.sizes), []
    for width, height in wanted:
        per_view = [
            timed(
                partial(
                    render_labels,
                    g,
                    c.scaled(width, height),
                    labels,
                    2,
                    min_weight=0.5,
                    backend=backend,
                ),
                args.repeats,
                args.device,
            )
            for c in cams
        ]
        rows.append(
            {
                "scene": name,
                "size": f"{width}x{height}",
                "views": len(cams),
                "ms_per_view": 1000 * statistics.median(per_view),
            }
        )
    table = pd.DataFrame(rows)
    table["ratio"] = table.ms_per_view / table.ms_per_view.iloc[0]
    table["pixel_ratio"] = [w * h / (wanted[0][0] * wanted[0][1]) for w, h in wanted]
    machine = describe_device(args.device)
    print(
        f"label render by size: {backend} on {machine.get('gpu') or machine.get('cpu')}, "
        f"{torch.get_num_threads()} threads, load {machine.get('load_average_1m')}"
    )
    print(table.to_markdown(index=False, floatfmt=".1f"))
    atomic_write_text(args.out, table.to_csv(index=False))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
