"""The student's cost per training step with and without the weight average, in one process.

    python -m bench.speed.student_step [--span 60] [--batch 8] [--crop 128] [--steps 10]
                                       [--rounds 3] [--out reports/bench_student_step.csv]

Two of the project's students (`RefinementTrainer.train_step`, the default architecture, two
classes) train on the same batch of random views, one of them folding its weights into their
average over `--span` steps after each step (`refine.ema_span`); they take turns, `--steps`
steps each per round, for `--rounds` rounds. A row's figure is the median of its rounds' ms per
step, and the average's own update is timed apart. --quick: 32 px crops, batch 2, 2 steps, one
round (what the tests run).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import pandas as pd
import torch

from bench import OUT_HELP, print_and_write
from sagonline.core.machine import describe_device
from sagonline.refine import RefineConfig, RefinementTrainer


class Student:
    """The project's student trainer on one batch of random views, with or without a weight
    average, its update timed apart."""

    def __init__(self, span: int, batch: int, crop: int):
        gen = np.random.default_rng(0)
        frames = list(gen.integers(0, 256, (batch, crop, crop, 3), dtype=np.uint8))
        masks = list(gen.integers(0, 2, (batch, crop, crop)))
        cfg = RefineConfig(batch_size=batch, crop=crop, ema_span=span)
        self.trainer = RefinementTrainer(cfg, 2, frames, masks, masks)
        self.batch = (self.trainer.rgb, self.trainer.coarse, self.trainer.teacher)
        self.update_s: list[float] = []
        if self.trainer.average is not None:
            update = self.trainer.average.update

            def timed(model) -> None:
                t = time.perf_counter()
                update(model)
                self.update_s.append(time.perf_counter() - t)

            self.trainer.average.update = timed

    def steps(self, n: int) -> float:
        """Seconds per step over `n` steps, the average's update included."""
        start = time.perf_counter()
        for _ in range(n):
            self.trainer.train_step(*self.batch)
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
    students = {
        "trained weights": Student(0, args.batch, args.crop),
        f"with ema_span={args.span}": Student(args.span, args.batch, args.crop),
    }
    for student in students.values():
        student.steps(1)  # warm up
    times: dict[str, list[float]] = {name: [] for name in students}
    for _ in range(args.rounds):
        for name, student in students.items():
            times[name].append(student.steps(args.steps))
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
    print_and_write(table, args.out)
    return table


if __name__ == "__main__":
    main()
