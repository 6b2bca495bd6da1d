"""The viewer in a real browser (headless Chromium): the page draws the splats, a click sent
through the browser labels Gaussians on the Python side, and the Export button writes object
PLYs that keep every property of the input file."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from bench.speed.browser import missing_browser_reason

pytestmark = pytest.mark.skipif(
    missing_browser_reason() is not None, reason=str(missing_browser_reason())
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def viewer(tmp_path):
    """The iced donut written as a PLY (with an extra property), 8 views, served on a free
    port; yields (app, session, ply path, parts)."""
    from plyfile import PlyData, PlyElement

    from sagonline.apps.viewer.app import ViewerApp
    from sagonline.apps.viewer.session import SegmentSession
    from sagonline.scene.io import read_scene, write_ply
    from sagonline.scene.trajectory import orbit_around
    from tests.segment.test_clicks import iced_donut

    g, parts = iced_donut(60, 28)
    ply = write_ply(tmp_path / "donut.ply", g)
    data = PlyData.read(str(ply)).elements[0].data
    extra = np.empty(len(data), data.dtype.descr + [("confidence", "f4")])
    for name in data.dtype.names:
        extra[name] = data[name]
    extra["confidence"] = np.linspace(0, 1, len(data))
    PlyData([PlyElement.describe(extra, "vertex")]).write(str(ply))
    g = read_scene(ply)
    ring, _ = orbit_around(g.means, 8, width=96, height=72)
    session = SegmentSession(g, ring, backend="native")
    app = ViewerApp(session, scene=ply, out=str(tmp_path / "export"), port=free_port())
    yield app, session, ply, parts
    session.stop()
    app.server.stop()


@pytest.mark.slow
def test_click_in_the_browser_labels_and_exports(viewer, tmp_path):
    from plyfile import PlyData

    from bench.speed import browser

    app, session, ply, parts = viewer
    chrome = browser.open_browser(app.url, 900, 600)
    try:
        browser.wait_for(lambda: app.server.get_clients(), 30, "the page to connect")
        browser.wait_for(lambda: browser.canvas(chrome), 30, "the scene's canvas")
        shot = browser.wait_for(
            lambda: colours(browser.screenshot(chrome, tmp_path / "page.png")) > 1,
            30,
            "the canvas to draw",
        )
        assert shot
        # aim the browser's camera from behind view 0 at an icing Gaussian, click the centre
        means = session.gaussians.means
        icing = means[(parts == 2) & (means[:, 2] > 0.38)]  # the top of the tube, facing up
        cam = session.cameras[0]
        target = icing[(icing - cam.center).norm(dim=1).argmin()].numpy()
        for client in app.server.get_clients().values():
            client.camera.position = target + 1.5 * (cam.center.numpy() - target)
            client.camera.look_at = target
        browser.wait_for(
            lambda: all(
                np.allclose(c.camera.look_at, target, atol=1e-3)
                for c in app.server.get_clients().values()
            ),
            10,
            "the camera to move",
        )
        browser.click_canvas(chrome)
        browser.wait_for(lambda: session.progress.state == "done", 60, "the labels")
        labelled = session.labels == 1
        assert labelled.sum() > 50 and app.updates > 0
        picked = np.linalg.norm(means.numpy() - session.clicks[0].point, axis=1).argmin()
        assert parts[picked] == 2  # the click landed where the browser's camera looked: icing
        browser.click_button(chrome, "Export objects, labels, recording")
        out = tmp_path / "export"
        browser.wait_for(lambda: (out / "objects" / "object.ply").is_file(), 60, "the export")
        assert browser.console_errors(chrome) == []  # the page logged no error of ours
    finally:
        chrome.quit()
    written = PlyData.read(str(out / "objects" / "object.ply")).elements[0]
    given = PlyData.read(str(ply)).elements[0]
    assert set(p.name for p in given.properties) <= set(p.name for p in written.properties)
    assert written.count == int(labelled.sum())


def colours(path) -> int:
    from PIL import Image

    pixels = np.asarray(Image.open(path).convert("RGB")).reshape(-1, 3)
    return len(np.unique(pixels, axis=0))
