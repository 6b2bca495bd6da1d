"""Progress of long work, said whether or not anyone watches a terminal.

On a terminal: a bar (tqdm). Elsewhere (a log file, CI, a pipe): one plain line when the work
starts, then at most one every `every` seconds (views done, elapsed, time left), and one when it
ends, so no run is silent for minutes.
"""

from __future__ import annotations

import sys
import time
from collections import deque
from collections.abc import Iterable, Iterator
from typing import TextIO, TypeVar

T = TypeVar("T")


class Progress:
    """`update()` once per item of `total`; `close()` at the end (a context manager too)."""

    def __init__(
        self,
        what: str,
        total: int,
        *,
        enabled: bool = True,
        every: float = 15.0,
        out: TextIO | None = None,
        terminal: bool | None = None,
        initial: int = 0,
    ):
        self.what, self.total, self.every = what, total, every
        self.out = out or sys.stderr
        self.enabled = enabled and total > 0
        self.terminal = self.out.isatty() if terminal is None else terminal
        self.done, self.initial, self.start = initial, initial, time.perf_counter()
        self._last = self.start
        self._recent: deque[tuple[float, int]] = deque(maxlen=8)  # (time, done) of the last items
        self._bar = None
        if not self.enabled:
            return
        if self.terminal:
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=what, leave=False, file=self.out)
        else:
            since = f" (from {initial})" if initial else ""
            self._say(f"{what}: {total - initial} to do{since}")

    def _say(self, line: str) -> None:
        print(line, file=self.out, flush=True)

    def update(self, n: int = 1, detail: str = "") -> None:
        """`n` more items done; `detail` (a loss, say) is shown beside the count."""
        self.done += n
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(n)
            if detail:
                self._bar.set_postfix_str(detail, refresh=False)
            return
        now = time.perf_counter()
        self._recent.append((now, self.done))
        if now - self._last >= self.every and self.done < self.total:
            self._last = now
            elapsed = now - self.start
            self._say(
                f"{self.what}: {self.done} of {self.total} ({elapsed:.0f} s, {self._left(now)})"
                + (f"; {detail}" if detail else "")
            )

    def _left(self, now: float) -> str:
        """The time left at the pace of the last items (the first ones of a model's run, or of
        a stage that found some cached, say nothing of the rest), or 'time left unknown' while
        fewer than three items are done."""
        (t0, d0), (t1, d1) = self._recent[0], self._recent[-1]
        if d1 - self.initial < 3 or d1 <= d0 or t1 <= t0:
            return "time left unknown"
        per_item = (t1 - t0) / (d1 - d0)
        return f"about {per_item * (self.total - self.done):.0f} s left"

    def close(self) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.close()
        else:
            self._say(
                f"{self.what}: {self.done} of {self.total} done in "
                f"{time.perf_counter() - self.start:.1f} s"
            )
        self.enabled = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress(items: Iterable[T], what: str, total: int, **options) -> Iterator[T]:
    """`items` with a `Progress` (see the class) kept as they pass."""
    with Progress(what, total, **options) as bar:
        for item in items:
            yield item
            bar.update()
