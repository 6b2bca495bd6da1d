"""What recording a trajectory frame costs a Stage I view on the host: the caller's time of
`Recorder.trajectory_frame` (a JPEG-encoded frame, its mask and its camera), three ways.

    python -m bench.speed.recording [--size 960x540] [--views 40] [--out F.csv] [--quick]

- as first written: rerun's own JPEG encoder, on the caller's thread;
- on the caller's thread: OpenCV's JPEG encoder (`Recorder._rgb`), still on that thread;
- handed over: `Recorder.trajectory_frame` as it is, the frame handed to the recorder's thread.
Between frames the caller sleeps 15 ms, a view's other work on a GPU. Per way: the median ms
a view, the time `close` then takes (the frames still waiting, the file written out) and the
file's size. The frame is smooth noise and the mask a box. --quick: 4 views at 96x54 (what the
tests run). Times on this machine; say what else ran.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from sagonline.core.files import atomic_write_text
from sagonline.record.recording import Recorder
from sagonline.scene.generator import make_scene

WAYS = ("as first written", "on the caller's thread", "handed over")


def first_rgb(recorder: Recorder, path: str, rgb: np.ndarray) -> None:
    """A frame logged as first written: rerun's JPEG encoder (quality 90)."""
    recorder.rec.log(path, recorder.rr.Image(np.ascontiguousarray(rgb)).compress(jpeg_quality=90))


def time_way(way: str, frame: np.ndarray, mask: np.ndarray, cameras, views: int) -> dict:
    """One way's row: ms a view (median), ms to close, MB written."""
    with tempfile.TemporaryDirectory() as folder:
        recorder = Recorder(Path(folder) / "recording.rrd", scenes=["bench"])
        recorder.annotate("bench", ["background", "object"])
        if way == "as first written":
            recorder._rgb = lambda path, rgb: first_rgb(recorder, path, rgb)  # type: ignore[method-assign]
        call = recorder.trajectory_frame if way == "handed over" else recorder._trajectory_frame
        took = []
        for index in range(views):
            start = time.perf_counter()
            call("bench", index, frame, mask, cameras[index % len(cameras)])
            took.append(time.perf_counter() - start)
            time.sleep(0.015)
        start = time.perf_counter()
        recorder.close()
        closing = time.perf_counter() - start
        size = (Path(folder) / "recording.rrd").stat().st_size
    return {
        "way": way,
        "ms_a_view": 1000 * statistics.median(took),
        "close_ms": 1000 * closing,
        "file_MB": size / 1e6,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="960x540", help="WIDTHxHEIGHT")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--out", type=Path, default=None, help="also write the table as CSV")
    ap.add_argument("--quick", action="store_true", help="4 views at 96x54")
    args = ap.parse_args()
    width, _, height = ("96x54" if args.quick else args.size).partition("x")
    views = 4 if args.quick else args.views
    if not (width.isdigit() and height.isdigit()) or views < 1:
        ap.error("--size WIDTHxHEIGHT (e.g. 960x540) and --views >= 1")
    w, h = int(width), int(height)
    noise = np.random.default_rng(0).integers(0, 256, (h, w, 3), np.uint8)
    frame = cv2.GaussianBlur(noise, (9, 9), 3)
    mask = np.zeros((h, w), np.int64)
    mask[h // 5 : h // 2, w // 5 : w // 2] = 1
    cameras = make_scene(num_gaussians=2000, width=w, height=h, num_train_views=4).train_cameras
    table = pd.DataFrame([time_way(way, frame, mask, cameras, views) for way in WAYS])
    print(f"Recording a trajectory frame, {w}x{h}, {views} views:\n")
    print(table.to_markdown(index=False, floatfmt=".3g"))
    if args.out is not None:
        atomic_write_text(args.out, table.assign(size=f"{w}x{h}").to_csv(index=False))


if __name__ == "__main__":
    main()
