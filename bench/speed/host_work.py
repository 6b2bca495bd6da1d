"""What a GPU would be asked to launch, counted on the CPU: PyTorch operations and host reads
(each a wait on the GPU) per fit step and per rendered view on the gsplat path.

    python -m bench.speed.host_work [--gaussians 36000] [--size 456x342] [--steps 20]
                                    [--out reports/host_work.csv] [--quick]

On a GPU a fit step or a view of this size is bound by the host: on an H200 the GPU recipe took
26.4 ms a step at 456 px and `fit=paper` 29.1 ms at 1296 px, where gsplat's kernels take a few.
Each operation costs the host about the same whatever the tensor's size, and each host read
waits for the GPU to finish what was queued, so their counts say what a step costs there. They
are counted here with gsplat's functions stood in for (`StandInGsplat`: they keep what they are
given and draw nothing, so gsplat's own launches are not in the counts) and the choices the code
makes on CUDA taken (SH colours by monomials, `render.sh`; Adam fused, `fitting.trainer`).

A fit step is the GPU recipe's (2DGS, distortion and normal regularisers on, SH degree 3) on a
generated scene, past densification; its parts: render (SH colours and gsplat's call), the loss
terms, backward, the densification statistics, the optimiser, the rest (the step's bookkeeping).
A view is an image render as Stage I asks for it. Top-level operations only (one an operation
calls inside itself is not counted again). --quick: 2,000 Gaussians at 48x36, 3 steps.
"""

from __future__ import annotations

import argparse
import collections
from contextlib import ExitStack
from unittest import mock

import pandas as pd
import torch

from bench import OUT_HELP, REPORTS, print_and_write
from sagonline.fitting import FitConfig, SceneFitter
from sagonline.render import api, projection
from sagonline.render.rasterize import rasterize
from sagonline.render.sh import eval_sh_monomials
from sagonline.scene.generator import make_scene

HOST_READS = ("aten::_local_scalar_dense", "aten::nonzero")  # a value the host waits for
# operations whose host reads are the CPU kernel's own (the fused Adam reads its step counter
# there; CUDA's kernel reads it on the device)
READS_ON_THE_DEVICE_ON_CUDA = ("aten::_fused_adam_",)


class StandInGsplat:
    """gsplat's two image functions as the backend calls them, on the CPU: they keep the colours
    they are given and draw nothing (what the backend does around gsplat, without CUDA)."""

    def __init__(self):
        self.colors: list[torch.Tensor] = []

    def _draw(self, colors, width, height, **kw):
        self.colors.append(colors)
        depth_too = colors.shape[-1] + 1  # render_mode RGB+D
        img = torch.zeros(1, height, width, depth_too) + colors.sum() * 0
        return img, torch.zeros(1, height, width, 1), {}

    def rasterization(self, means, quats, scales, opacities, colors, **kw):
        return self._draw(colors, **kw)

    def rasterization_2dgs(self, means, quats, scales, opacities, colors, **kw):
        assert colors.dim() == 3  # per-camera colours, (C, N, D)
        img, alphas, meta = self._draw(colors[0], **kw)
        return img, alphas, None, None, None, None, meta

    def rasterize_to_indices_in_range(self, *args):  # a trace's: not reached by an image
        raise AssertionError("an image-only render walked gsplat's tile lists")

    rasterize_to_indices_in_range_2dgs = rasterize_to_indices_in_range


def as_on_cuda(stack: ExitStack) -> None:
    """gsplat stood in for and taken as available; SH colours as CUDA computes them."""
    stack.enter_context(mock.patch.dict("sys.modules", {"gsplat": StandInGsplat()}))
    stack.enter_context(mock.patch.object(torch.cuda, "is_available", lambda: True))
    stack.enter_context(mock.patch.object(api, "resolve_backend", lambda backend, device: backend))
    stack.enter_context(mock.patch.object(projection, "eval_sh", eval_sh_monomials))


def in_part(part: str, fn):
    """fn, its operations counted under `part` (the innermost part that holds them)."""

    def wrapped(*args, **kwargs):
        with torch.profiler.record_function("PART:" + part):
            return fn(*args, **kwargs)

    return wrapped


def count(run, times: int) -> dict[str, tuple[float, float]]:
    """Per call of run(): {part: (top-level operations, host reads)} (`in_part`'s parts; the
    rest is "rest")."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(times):
            run()
    ops, reads = collections.Counter(), collections.Counter()
    for event in prof.events():
        if not event.name.startswith("aten::"):
            continue
        part, nested, up = "rest", False, event.cpu_parent
        cpu_own = False
        while up is not None:
            nested = nested or up.name.startswith("aten::")
            cpu_own = cpu_own or up.name in READS_ON_THE_DEVICE_ON_CUDA
            if up.name.startswith("PART:"):
                part = up.name[5:]
                break
            up = up.cpu_parent
        ops[part] += not nested
        reads[part] += event.name in HOST_READS and not cpu_own
    return {part: (ops[part] / times, reads[part] / times) for part in ops}


def fit_step_counts(args) -> dict[str, tuple[float, float]]:
    """A GPU-recipe fit step's operations and host reads, by part."""
    s = make_scene(
        layout="forward",
        num_gaussians=max(args.gaussians // 4, 500),
        width=args.width,
        height=args.height,
        num_train_views=6,
        num_eval_views=1,
    )
    photos = [rasterize(s.gaussians, c).rgb.clamp(0, 1) for c in s.train_cameras]
    cfg = FitConfig(
        init_points=args.gaussians,
        background_points=0,
        holdout_every=10**6,
        backend="gsplat",
        checkpoint_every=10**9,
    )
    fitter = SceneFitter(cfg, s.train_cameras, photos)
    fitter.step = cfg.densify_until + 1  # past the regularisers' starts and densification
    groups = [{k: g[k] for k in ("params", "lr", "name")} for g in fitter.optim.param_groups]
    fitter.optim = torch.optim.Adam(groups, eps=1e-15, fused=True)  # as `_set_params` on CUDA
    fitter.render = in_part("render", fitter.render)
    fitter.loss = in_part("loss terms", fitter.loss)
    fitter.strategy.after_backward = in_part(
        "densification statistics", fitter.strategy.after_backward
    )
    fitter.optim.step = in_part("optimiser", fitter.optim.step)
    views = iter(range(10**9))

    def step():
        fitter.train_step(fitter.train_idx[next(views) % len(fitter.train_idx)], 0.5)
        fitter.step += 1

    step()  # warm
    with mock.patch.object(torch.Tensor, "backward", in_part("backward", torch.Tensor.backward)):
        return count(step, args.steps)


def view_counts(args) -> dict[str, tuple[float, float]]:
    """An image render's operations and host reads, as Stage I asks for a view."""
    s = make_scene(layout="360", num_gaussians=args.gaussians, width=args.width, height=args.height)
    cam = s.train_cameras[0]
    api.render(s.gaussians, cam, backend="gsplat")
    return count(lambda: api.render(s.gaussians, cam, backend="gsplat"), args.steps)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--gaussians", type=int, default=36_000)
    ap.add_argument("--size", default="456x342", help="WxH of the photographs and the view")
    ap.add_argument("--steps", type=int, default=20, help="steps (and renders) counted")
    ap.add_argument("--quick", action="store_true", help="2,000 Gaussians at 48x36, 3 steps")
    ap.add_argument("--out", default=str(REPORTS / "host_work.csv"), help=OUT_HELP)
    args = ap.parse_args()
    if args.quick:
        args.gaussians, args.size, args.steps = 2_000, "48x36", 3
    try:
        args.width, args.height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        raise SystemExit(f"error: --size {args.size!r}: WxH, say 456x342") from None
    rows = []
    with ExitStack() as stack:
        as_on_cuda(stack)
        for what, counts in (("fit step", fit_step_counts(args)), ("view", view_counts(args))):
            for part, (ops, reads) in sorted(counts.items(), key=lambda kv: -kv[1][0]):
                rows.append({"what": what, "part": part, "operations": ops, "host reads": reads})
            total = [sum(v[i] for v in counts.values()) for i in (0, 1)]
            rows.append(
                {"what": what, "part": "all", "operations": total[0], "host reads": total[1]}
            )
    table = pd.DataFrame(rows).assign(gaussians=args.gaussians, size=args.size)
    table[["operations", "host reads"]] = table[["operations", "host reads"]].round(1)
    print_and_write(table, args.out)


if __name__ == "__main__":
    main()
