"""The student's cost per training step with and without the weight average, in one process.

    python -m bench.speed.student_step [--span 60] [--batch 8] [--crop 128] [--steps 10]
                                       [--rounds 3] [--out reports/bench_student_step.csv]

Two students of the default architecture (`refine.encoder=resnet18`, two classes) train on the
same random batches, one of them folding its weights into a `WeightAverage` of `--span` steps
after each step (`refine.ema_span`); they take turns, `--steps` steps each per round, for
`--rounds` rounds. A row's figure is the median of its rounds' ms per step, and the average's
own update is timed apart. --quick: 32 px crops, batch 2, 2 steps, one round (what the tests
run).
"""

from __future__ import annotations

import argparse
import statistics
import time

import pandas as pd
import torch
import torch.nn.functional as F

from bench import OUT_HELP
from sagonline.core.files import atomic_write_text
from sagonline.core.machine import describe_device
from sagonline.refine.network import DualBranchRefiner
from sagonline.refine.weight_average import WeightAverage


class Student:
    """A student and its optimiser, with or without a weight average."""

    def __init__(self, span: int):
        torch.manual_seed(0)
        self.net = DualBranchRefiner(2)
        self.optim = torch.optim.Adam(self.net.parameters(), lr=1e-3)
        self.average = WeightAverage(self.net, span) if span else None
        self.update_s: list[float] = []

    def steps(self, batch: tuple[torch.Tensor, ...], n: int) -> float:
        """Seconds per step over `n` steps, the average's update included."""
        rgb, coarse, target = batch
        start = time.perf_counter()
        for _ in range(n):
            loss = F.cross_entropy(self.net(rgb, coarse), target)
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self.optim.step()
            if self.average is not None:
                t = time.perf_counter()
                self.average.update(self.net)
                self.update_s.append(time.perf_counter() - t)
        return (time.perf_counter() - start) / n


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(prog="python -m bench.speed.student_step", description=__doc__)
    ap.add_argument("--span", type=int, default=60, help="refine.ema_span (60)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--crop", type=int, default=128)
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None, help=OUT_HELP)
    args = ap.parse_args(argv)
    if args.quick:
        args.batch, args.crop, args.steps, args.rounds = 2, 32, 2, 1
    if args.span < 1:
        ap.error("--span must be >= 1")
    gen = torch.Generator().manual_seed(0)
    size = (args.batch, args.crop, args.crop)
    batch = (
        torch.rand(args.batch, 3, args.crop, args.crop, generator=gen),
        torch.rand(args.batch, 2, args.crop, args.crop, generator=gen),
        torch.randint(0, 2, size, generator=gen),
    )
    students = {"trained weights": Student(0), f"with ema_span={args.span}": Student(args.span)}
    for student in students.values():
        student.steps(batch, 1)  # warm up
    times: dict[str, list[float]] = {name: [] for name in students}
    for _ in range(args.rounds):
        for name, student in students.items():
            times[name].append(student.steps(batch, args.steps))
    plain = statistics.median(times["trained weights"])
    machine = describe_device()
    rows = [
        {
            "student": name,
            "ms_per_step": round(1000 * statistics.median(t), 1),
            "ratio_to_plain": round(statistics.median(t) / plain, 3),
            "average_update_ms": (
                round(1000 * statistics.median(s.update_s), 2) if s.update_s else None
            ),
            "rounds": len(t),
            "steps_per_round": args.steps,
            "batch": args.batch,
            "crop": args.crop,
            "threads": torch.get_num_threads(),
            "device": machine["cpu"],
            "load_average_1m": machine["load_average_1m"],
        }
        for (name, t), s in zip(times.items(), students.values(), strict=True)
    ]
    table = pd.DataFrame(rows)
    print(table.to_string(index=False))
    if args.out:
        atomic_write_text(args.out, table.to_csv(index=False))
        print(f"wrote {args.out}")
    return table


if __name__ == "__main__":
    main()
