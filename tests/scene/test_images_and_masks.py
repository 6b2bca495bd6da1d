"""Images and masks: a PNG bomb is refused from its header; masks are read as what they are and
resized pixel-centred; a file that is no mask is refused with what was seen."""

from __future__ import annotations

import resource

import cv2
import numpy as np
import pytest

from tests.refusals import bomb_png, one_error_line, run_python


def test_a_png_bomb_is_refused_from_its_header_at_little_memory(tmp_path):
    """A 93 KB PNG of 32000x24000 1-bit pixels cost 42 s and 9.3 GB of memory to score."""
    gt = tmp_path / "gt" / "s"
    pred = tmp_path / "pred" / "s"
    gt.mkdir(parents=True)
    pred.mkdir(parents=True)
    cv2.imwrite(str(gt / "v.png"), np.zeros((30, 40), np.uint8))
    bomb_png(pred / "v.png", 32000, 24000)
    assert (pred / "v.png").stat().st_size < 200_000
    code, err, peak = run_python("sagonline", "score", str(tmp_path / "pred"), str(tmp_path / "gt"))
    assert code == 2, err
    one_error_line(err, "v.png", "exceeds the ceiling", "refused before decoding")
    assert 0 < peak < 1500, peak  # torch and the libraries alone are about 500 MB


def test_memory_of_the_test_process_is_bounded():
    """The hostile files above were refused before their pixels were decoded: this process
    never grew past a few gigabytes."""
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss < 6 * 1024 * 1024


@pytest.mark.parametrize(
    ("make", "kind", "objects"),
    [
        ("binary", "binary", 1),
        ("antialiased", "binary", 1),
        ("jpeg", "binary", 1),
        ("rgba_cutout", "binary", 1),
        ("grey_as_rgb", "binary", 1),
        ("labels", "label map", 2),
        ("labels_void", "label map", 3),
    ],
)
def test_masks_are_read_as_what_they_are(tmp_path, make, kind, objects):
    from sagonline.scene.io.masks import read_mask

    disc = np.zeros((60, 80), np.uint8)
    cv2.circle(disc, (40, 30), 15, 255, -1)
    labels = np.zeros((60, 80), np.uint8)
    labels[5:20, 5:20], labels[30:50, 40:70] = 1, 2
    image = {
        "binary": disc,
        "antialiased": cv2.GaussianBlur(disc, (9, 9), 2.0),
        "jpeg": disc,
        "rgba_cutout": np.dstack([np.full((60, 80, 3), 200, np.uint8), disc]),
        "grey_as_rgb": np.dstack([disc] * 3),
        "labels": labels,
        "labels_void": np.where(np.arange(60)[:, None] < 3, 255, labels).astype(np.uint8),
    }[make]
    path = tmp_path / ("m.jpg" if make == "jpeg" else "m.png")
    cv2.imwrite(str(path), image)
    read = read_mask(path)
    assert read.kind == kind
    assert len(np.unique(read.labels)) - 1 == objects
    if kind == "binary":
        assert abs(int(read.labels.sum()) - int((disc > 127).sum())) <= 30


@pytest.mark.parametrize(
    ("image", "seen"),
    [
        (np.random.default_rng(0).integers(0, 255, (30, 40, 3)).astype(np.uint8), "3 channels"),
        (
            np.dstack(
                [
                    np.random.default_rng(1).integers(0, 9, (30, 40, 3)).astype(np.uint8),
                    np.full((30, 40), 255, np.uint8),
                ]
            ),
            "4 channels",
        ),
        (np.arange(1200, dtype=np.uint16).reshape(30, 40), "1200 distinct values"),
    ],
)
def test_a_file_that_is_no_mask_is_refused_with_what_was_seen(tmp_path, image, seen):
    from sagonline.scene.io.masks import MaskFileError, read_mask

    cv2.imwrite(str(tmp_path / "m.png"), image)
    with pytest.raises(MaskFileError, match=seen):
        read_mask(tmp_path / "m.png")


def centre_of(mask: np.ndarray) -> tuple[float, float]:
    """(x, y) mean of the mask's pixel centres."""
    ys, xs = np.nonzero(mask)
    return float(xs.mean() + 0.5), float(ys.mean() + 0.5)


@pytest.mark.parametrize("side", [228, 57, 2400])
def test_a_resized_mask_keeps_its_place(side):
    """A centred square shrunk 1000 -> 228 px stays centred (protocol 2). OpenCV's
    INTER_NEAREST (protocol 1) drew it at 114.5, half a pixel right and down."""
    from sagonline.datasets.common import click_prompt
    from sagonline.scene.io.images import resize_nearest

    mask = np.zeros((1000, 1000), np.uint8)
    mask[300:700, 300:700] = 1
    assert centre_of(resize_nearest(mask, (side, side))) == (side / 2, side / 2)
    prompt = click_prompt(mask, 0, 2, 3, seed=0, scale=(side / 1000, side / 1000))
    assert centre_of(prompt.objects[0].mask) == (side / 2, side / 2)


def test_the_resize_is_pils_nearest_neighbour():
    """Any size to any size, labels and dtype kept: the same pixels as PIL's nearest."""
    from PIL import Image

    from sagonline.scene.io.images import resize_nearest

    rng = np.random.default_rng(0)
    for _ in range(50):
        (h, w), (th, tw) = rng.integers(1, 300, (2, 2))
        labels = rng.integers(0, 250, (h, w)).astype(np.int64)
        resized = resize_nearest(labels, (int(th), int(tw)))
        expected = Image.fromarray(labels.astype(np.uint8)).resize((int(tw), int(th)), 0)
        assert resized.dtype == np.int64 and np.array_equal(resized, np.asarray(expected))


@pytest.mark.parametrize(
    "plane",
    [
        np.random.default_rng(0).integers(0, 256, (37, 53)).astype(np.uint8),
        np.random.default_rng(1).choice([0, 3, 65535], (40, 30)).astype(np.uint16),
        np.dstack([np.full((9, 7), 5, np.uint8), np.eye(9, 7, dtype=np.uint8) * 200])[..., 1],
        np.zeros((0, 4), np.uint8),
        np.array([[-1, 4], [4, 9]], np.int64),
    ],
    ids=["uint8", "uint16", "a channel's strided view", "empty", "int64"],
)
def test_a_planes_distinct_values_are_numpys(plane):
    """The histogram's values (8- and 16-bit planes) are `np.unique`'s, in its dtype."""
    from sagonline.scene.io.masks import distinct_values

    got, want = distinct_values(plane), np.unique(plane)
    assert got.dtype == want.dtype and np.array_equal(got, want)
