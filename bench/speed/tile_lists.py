"""One view's tile lists for the Triton walks, made two ways: PyTorch's operators
(`triton_vote.tile_view`) and `triton_prepare`'s two kernels (`tile_view_fused`), on
`bench.speed.render`'s scenes: the PyTorch operators each dispatches (views aside; on a GPU each
is at least one launch), its Triton launches, its reads of a value back to the host, ms per
view, and whether the two lists are the same (on a GPU a fused multiply-add may move a box edge
or a depth by its last bit: `tests/render/test_triton_prepare.py` says how far apart they may
be).

    python -m bench.speed.tile_lists [--device cuda] [--repeats 5] [--out F.csv] [--quick]

On the CPU the Triton kernels run in Triton's interpreter: the counts hold there, the times
say nothing of a GPU's.
"""

from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path
from unittest import mock

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from bench.speed.render import scenes, show_table, timed
from sagonline.render import triton_prepare
from sagonline.render.triton_vote import TiledView, tile_view

KERNELS = ("_project_kernel", "_emit_kernel")


class OperatorCount(TorchDispatchMode):
    """Counts the PyTorch operators dispatched inside it that return no view, outside the
    Triton launches it is told of (the interpreter's own tensor work is not the method's)."""

    def __init__(self) -> None:
        super().__init__()
        self.operators, self.host_reads, self.launches, self.paused = 0, 0, 0, False

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        schema = func._schema
        view = not schema.is_mutable and any(r.alias_info for r in schema.returns)
        if not self.paused and not view:
            self.operators += 1
            self.host_reads += str(func.overloadpacket) in (
                "aten._local_scalar_dense",
                "aten.nonzero",
            )
        return func(*args, **(kwargs or {}))

    def launch(self, kernel):
        """`kernel` (a Triton kernel) whose launches are counted and not looked into."""
        count = self

        class Counted:
            def __getitem__(self, grid):
                def run(*args, **kwargs):
                    count.launches, count.paused = count.launches + 1, True
                    try:
                        return kernel[grid](*args, **kwargs)
                    finally:
                        count.paused = False

                return run

        return Counted()


def counted(make, g, camera) -> tuple[TiledView, OperatorCount]:
    """`make(g, camera, 0.01, with_colors=False)`'s view, and what it dispatched."""
    count = OperatorCount()
    launches = {name: count.launch(getattr(triton_prepare, name)) for name in KERNELS}
    with mock.patch.multiple(triton_prepare, **launches), count:
        view = make(g, camera, 0.01, with_colors=False)
    if view is None:
        raise SystemExit("nothing of the scene is in its first view")
    return view, count


def scene_rows(name: str, g, camera, repeats: int, device: str) -> list[dict]:
    """A row for each way on one scene's first view."""
    rows, views = [], {}
    for way, make in (("torch", tile_view), ("fused", triton_prepare.tile_view_fused)):
        views[way], count = counted(make, g, camera)  # also the warm-up of the timed calls
        again = partial(make, g, camera, 0.01, with_colors=False)
        ms = 1000 * timed(again, repeats, device, warmup=lambda: None)
        rows.append(
            {
                "scene": name,
                "device": device,
                "tile lists": way,
                "splats": len(views[way].proj),
                "pairs": int(views[way].counts.sum()),
                "torch operators": count.operators,
                "triton launches": count.launches,
                "host reads": count.host_reads,
                "ms per view": ms,
            }
        )
    ref, got = views["torch"], views["fused"]
    same = torch.equal(ref.proj.ids, got.proj.ids) and torch.equal(ref.counts, got.counts)
    rows[-1]["same lists as torch"] = same and torch.equal(ref.order, got.order)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None, help="also write the table as a CSV")
    ap.add_argument("--quick", action="store_true", help="the tiny scenes, 1 repeat")
    args = ap.parse_args()
    if args.quick:
        args.repeats = 1
    rows = []
    for name, g, _, views in scenes(args.quick):
        rows += scene_rows(
            name, g.to(args.device), views[0].to(args.device), args.repeats, args.device
        )
    heading = f"One view's tile lists for the Triton walks, on {{where}}; median of {args.repeats}"
    show_table(rows, args.device, heading, args.out)


if __name__ == "__main__":
    main()
