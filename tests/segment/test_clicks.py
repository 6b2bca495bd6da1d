"""Clicks add information: on an iced donut (pink icing on brown dough, a black background), one
click, three clicks and three clicks plus a negative click on the dough all select the icing,
seen from a view between the segmented ones."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from sagonline.pipeline.segment import clicks_prompt, segment_scene
from sagonline.render import render_labels
from sagonline.scene.gaussians import SH_C0, Gaussians
from sagonline.scene.trajectory import orbit_around

ICING, DOUGH = (0.95, 0.45, 0.7), (0.6, 0.4, 0.2)


def iced_donut(n_u: int = 90, n_v: int = 40) -> tuple[Gaussians, torch.Tensor]:
    """A torus (radius 1, tube 0.4, z up) of small round Gaussians: the top of the tube pink (the
    icing, label 2), the rest brown (the dough, label 1). Returns the Gaussians and the labels
    (N,) int64 (0 is the empty background)."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n_u, False), np.linspace(0, 2 * np.pi, n_v, False))
    u, v = u.ravel(), v.ravel()
    ring = 1.0 + 0.4 * np.cos(v)
    means = np.stack([ring * np.cos(u), ring * np.sin(u), 0.4 * np.sin(v)], 1)
    icing = np.sin(v) > 0.5
    colours = np.where(icing[:, None], ICING, DOUGH)
    n = len(means)
    g = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        scales=torch.full((n, 3), 0.045),
        opacities=torch.full((n,), 0.95),
        sh=torch.tensor((colours - 0.5) / SH_C0, dtype=torch.float32)[:, None, :],
    )
    return g, torch.from_numpy(1 + icing.astype(np.int64))


@pytest.fixture(scope="module")
def donut():
    g, parts = iced_donut()
    ring, _ = orbit_around(g.means, 12, width=96, height=72)
    between, _ = orbit_around(g.means, 24, width=96, height=72)
    unseen = between[5]  # 75 degrees: halfway between two segmented views
    view0 = render_labels(g, ring[0], parts, 3, backend="native").numpy()
    return g, parts, ring, unseen, view0


def _pixels(mask: np.ndarray, count: int) -> list[tuple[float, float]]:
    """`count` pixel centres (x, y) spread along the mask, away from its edges."""
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8))
    ys, xs = np.nonzero(inner)
    order = np.argsort(xs)
    picks = order[np.linspace(0, len(order) - 1, count + 2).astype(int)[1:-1]]
    return [(float(xs[i]) + 0.5, float(ys[i]) + 0.5) for i in picks]


@pytest.mark.parametrize(("clicks", "negatives"), [(1, 0), (3, 0), (3, 1)])
def test_more_clicks_keep_the_icing(donut, clicks, negatives):
    g, parts, ring, unseen, view0 = donut
    positive = _pixels(view0 == 2, clicks)
    negative = _pixels(view0 == 1, negatives) if negatives else []  # on the dough
    prompt = clicks_prompt(ring, 0, {"icing": positive}, {"icing": negative})
    seg = segment_scene(g, ring, prompt, backend="native")
    truth = render_labels(g, unseen, parts, 3, backend="native").numpy() == 2
    pred = render_labels(g, unseen, torch.from_numpy(seg.labels), 2, backend="native").numpy() == 1
    iou = (pred & truth).sum() / (pred | truth).sum()
    assert iou >= 0.9, (clicks, negatives, iou)


def donut_icing(views: int):
    """The captured donut orbited by `views` views at 480x270 from its one camera, a view
    37.5 degrees from the first, and the icing there (its pink and blue sprinkles by hue):
    (gaussians, ring, unseen camera, truth (H, W) bool)."""
    import cv2

    from sagonline.render.api import render, to_uint8
    from sagonline.scene.io import read_scene
    from sagonline.scene.io.cameras import load_cameras
    from sagonline.scene.trajectory import ring_around
    from tests.fixtures import shared_data

    g = read_scene(shared_data("donut_3dgs", "point_cloud.ply"))
    cam = load_cameras(shared_data("donut_3dgs", "transforms.json"))[0].scaled(480, 270)
    centre = g.means.median(0).values.numpy()
    ring = ring_around(cam, centre, views)
    unseen = ring_around(ring_around(cam, centre, 48)[5], centre, 1)[0]
    out = render(g, unseen, backend="native")
    hsv = cv2.cvtColor(to_uint8(out.rgb), cv2.COLOR_RGB2HSV)
    pink = (hsv[..., 0] >= 135) & (hsv[..., 0] <= 178) & (hsv[..., 1] > 40)
    blue = (hsv[..., 0] >= 95) & (hsv[..., 0] <= 130) & (hsv[..., 1] > 60)
    closed = cv2.morphologyEx((pink | blue).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((7, 7)))
    truth = (closed > 0) & (out.alpha.reshape(closed.shape).numpy() > 0.5)
    return g, ring, unseen, truth


@pytest.mark.slow
def test_more_clicks_keep_the_icing_of_the_real_donut():
    """The captured donut (one camera, orbited): truth is the icing's pink and blue sprinkles by
    hue in a view 37.5 degrees from the prompt view, between two segmented views."""
    g, ring, unseen, truth = donut_icing(24)
    icing, dough = [(150, 60), (330, 50), (240, 40)], [(240, 135)]
    for positive, negative in [(icing[:1], []), (icing, []), (icing, dough)]:
        prompt = clicks_prompt(ring, 0, {"icing": positive}, {"icing": negative})
        seg = segment_scene(g, ring, prompt)
        labels = torch.from_numpy(seg.labels)
        pred = render_labels(g, unseen, labels, 2, backend="native").numpy() == 1
        iou = (pred & truth).sum() / (pred | truth).sum()
        assert iou >= 0.9, (len(positive), len(negative), iou)


def test_the_same_prompt_gives_the_same_masks_in_any_thread(donut):
    """GrabCut draws from OpenCV's per-thread RNG: seeded, a prompt's masks do not depend on
    earlier calls or on the thread (the viewer segments in a worker thread)."""
    import threading

    g, parts, ring, _, view0 = donut
    prompt = clicks_prompt(ring, 0, {"icing": _pixels(view0 == 2, 1)})
    runs = [segment_scene(g, ring, prompt, backend="native") for _ in range(2)]
    worker = threading.Thread(
        target=lambda: runs.append(segment_scene(g, ring, prompt, backend="native"))
    )
    worker.start()
    worker.join(120)
    for other in runs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(runs[0].masks, other.masks, strict=True))
        np.testing.assert_array_equal(runs[0].labels, other.labels)
