"""A segmenter's preparation of the viewer's views (a model's image embeddings) in a thread of
its own, started as soon as the views are rendered, so that a click costs the decoder and the
vote only. A click before it is done waits only for the views its run needs (the model embeds
one frame at a time and keeps what it made)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from sagonline.segment.base import VideoSegmenter


class Preparation:
    """`segmenter.prepare(frames)` in the background. done / total: the views prepared so far;
    seconds: how long all took (None until then); error: what failed it (the click's run
    meets the same failure and shows it). `current()` says whether this segmenter is still
    the session's (a replaced one stops after its view in hand); `on_progress(done, total)`
    hears of every view."""

    def __init__(
        self,
        segmenter: VideoSegmenter,
        frames: list[np.ndarray],
        current: Callable[[], bool],
        on_progress: Callable[[int, int], None] | None = None,
    ):
        self.done, self.total = 0, len(frames)
        self.seconds: float | None = None
        self.error: str | None = None
        self._current, self._on_progress = current, on_progress
        self._thread = threading.Thread(target=self._work, args=(segmenter, frames), daemon=True)
        self._thread.start()

    def _progress(self, done: int, total: int) -> bool:
        if not self._current():
            return False
        self.done = done
        if self._on_progress is not None:
            self._on_progress(done, total)
        return True

    def _work(self, segmenter: VideoSegmenter, frames: list[np.ndarray]) -> None:
        start = time.perf_counter()
        try:
            segmenter.prepare(frames, progress=self._progress)
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
            return
        if self._current():
            self.done, self.seconds = self.total, time.perf_counter() - start
            if self._on_progress is not None:
                self._on_progress(self.total, self.total)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every view is prepared (or `timeout` s); whether they are."""
        self._thread.join(timeout)
        return self.seconds is not None
