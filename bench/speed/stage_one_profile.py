"""Stage I's views under `torch.profiler`: where each part of a view (`bench.speed.stage_one`'s
columns) spends its time, on the host and on the device, and which operators and kernels take
most, so a part above what its model or kernel alone takes says whether the host or the GPU
holds it.

    python -m bench.speed.stage_one_profile [--device cuda] [--segmenter sam2_tiny]
        [--objects 1] [--views 12] [--option KEY=VALUE] [--top 15] [--out F.csv] [--quick]

The views run as `bench.speed.stage_one` runs them (the same scene, prompt and options), all
under the profiler; what began before the prompt view's last range ended (its one-off costs)
is left out of the figures. Per
part: its ms a view on the host (the range's CPU time, what it launched and waited for
included) and on the device (the kernels launched in its range), and the part's wall ms under
the profiler (which slows the host: compare the parts within this table, and take
`bench.speed.stage_one`'s columns for the times). Then the operators of most CPU time and the
kernels of most device time, a view. --quick: 3 views at 96x54, 4k surfels (the tests').
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch
from torch.autograd import DeviceType

from bench.speed.stage_one import (
    INNER_PARTS,
    PARTS,
    PROFILED,
    SEGMENTER_PARTS,
    time_views,
    view_arguments,
    views_asked,
)
from sagonline.core.files import atomic_write_text


def profile_views(
    segmenter: str, views: int, size, gaussians: int, objects: int, device: str, settings, top: int
) -> tuple[pd.DataFrame, str]:
    """`profile_table` of the views (`bench.speed.stage_one.time_views`'s) run under
    torch.profiler (its CUDA activity too on `device` cuda), and the weights that ran."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.startswith("cuda")
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        table, _, weights, _ = time_views(
            segmenter, views, size, gaussians, objects, device, settings
        )
    return profile_table(list(prof.events()), table, cuda, top), weights


def profile_table(events: list, table: pd.DataFrame, cuda: bool, top: int) -> pd.DataFrame:
    """Rows of kind "part" (each timed part's range: host ms, its CPU time with what it waited
    for; device ms, the kernels launched in it; wall ms, `table`'s under the profiler), "cpu"
    (the operators of most self CPU time) and "device" (the kernels and copies of most device
    time, then "all kernels"), ms a view over `table`'s views 1..: the events (torch.profiler's
    `FunctionEvent`s) that began after the prompt view's last range (its labels) ended."""
    prompt_end = min(e.time_range.end for e in events if e.name == f"{PROFILED}labels")
    later = [e for e in events if e.time_range.start >= prompt_end]
    n = int((table.view != 0).sum())
    steady = table[table.view != 0]

    def total(name: str, field: str) -> float:  # ms a view
        return sum(getattr(e, field) for e in later if e.name == name) / 1e3 / n

    rows = []
    for part in (*PARTS, *INNER_PARTS):
        name = f"{PROFILED}{'segmenter' if part == 'segment' else part}"
        if f"{part}_ms" not in table or not any(e.name == name for e in later):
            continue
        host, on_device = total(name, "cpu_time_total"), total(name, "device_time_total")
        if part == "segment":  # the segmenter's range less its timed parts
            for inner in SEGMENTER_PARTS:
                host -= total(f"{PROFILED}{inner}", "cpu_time_total")
                on_device -= total(f"{PROFILED}{inner}", "device_time_total")
        rows.append(
            {
                "kind": "part",
                "name": part,
                "host ms": host,
                "device ms": on_device if cuda else None,
                "wall ms": steady[f"{part}_ms"].mean(),
                # the segmenter's ranges count its last call too (the end of its views)
                "calls": sum(e.name == name for e in later) / n if part != "segment" else None,
            }
        )
    on_host = [e for e in later if e.device_type == DeviceType.CPU]
    # a kernel's time is its CPU operator's device time too: the device's own events alone
    kernels = [e for e in later if e.device_type != DeviceType.CPU]
    for kind, chosen, field in (
        ("cpu", [e for e in on_host if not e.name.startswith(PROFILED)], "self_cpu_time_total"),
        ("device", kernels, "device_time_total"),
    ):
        by_name: dict[str, list] = {}
        for e in chosen:
            if getattr(e, field) > 0:
                by_name.setdefault(e.name, []).append(getattr(e, field))
        largest = sorted(by_name.items(), key=lambda item: sum(item[1]), reverse=True)[:top]
        unit = "host ms" if kind == "cpu" else "device ms"
        for name, times in largest:
            rows.append({"kind": kind, "name": name[:90], unit: sum(times) / 1e3 / n})
            rows[-1]["calls"] = len(times) / n
    if cuda:
        busy = sum(e.device_time_total for e in kernels) / 1e3 / n
        rows.append({"kind": "device", "name": "all kernels", "device ms": busy})
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    view_arguments(ap, "sam2_tiny", views=12, objects=1)
    ap.add_argument("--top", type=int, default=15, help="operators and kernels listed")
    ap.add_argument("--out", type=Path, default=None, help="also write the table as a CSV")
    args = ap.parse_args()
    asked = views_asked(ap, args)
    try:
        table, weights = profile_views(*asked, args.top)
    except ValueError as exc:  # a missing model file names the option and `make weights`
        raise SystemExit(f"stage_one_profile: {exc}") from None
    gpu = torch.cuda.get_device_name(0) if args.device.startswith("cuda") else None
    print(
        f"Stage I under torch.profiler: {args.segmenter} (weights: {weights}) on "
        f"{gpu or args.device}, "
        f"{args.views} views at {args.size}, {args.objects} object(s); ms a view over views "
        f"1-{args.views - 1}\n"
    )
    print(table.round(3).to_markdown(index=False))
    if args.out is not None:
        named = {"segmenter": args.segmenter, "weights": weights}
        named |= {"options": " ".join(args.option), "gpu": gpu}
        atomic_write_text(args.out, table.assign(**named).to_csv(index=False))


if __name__ == "__main__":
    main()
