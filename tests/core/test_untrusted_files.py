"""Checkpoints and weights are read without running code: pickles planted in fits, students, YOLO
weights and user checkpoints are refused by name; a real checkpoint loads without trust."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.fixtures import (
    llff_scene,
)
from tests.refusals import (
    NAMES,
    plant,
)


def test_pickled_fit_and_student_checkpoints_never_run(tmp_path):
    from sagonline.fitting import FitConfig, SceneFitter
    from sagonline.refine import RefineConfig, RefinementTrainer

    marker = tmp_path / "ran.txt"
    fit_ckpt = plant(tmp_path / "fit_checkpoint.store", marker)
    cams, sc = llff_scene(tmp_path / "cap", NAMES, with_scene=False)
    imgs = [torch.rand(c.height, c.width, 3) for c in cams]
    fitter = SceneFitter(FitConfig(iterations=2, init_points=200, max_gaussians=400), cams, imgs)
    with pytest.warns(UserWarning, match="fit checkpoint unusable.*fit_checkpoint.store"):
        assert not fitter.resume(fit_ckpt)
    assert not fit_ckpt.exists() and not marker.exists()

    student = plant(tmp_path / "refine.store", marker, how="raw")
    frames = [np.zeros((32, 32, 3), np.uint8)] * 2
    masks = [np.zeros((32, 32), np.int64)] * 2
    with pytest.warns(UserWarning, match="student checkpoint unusable.*refine.store"):
        trainer = RefinementTrainer(RefineConfig(max_steps=2), 2, frames, masks, masks, student)
    assert trainer.step == 0 and not student.exists() and not marker.exists()


def test_pickled_yolo_weights_are_refused_by_name(tmp_path):
    pytest.importorskip("ultralytics")
    from sagonline.scene.io.checkpoints import UntrustedCheckpoint
    from sagonline.segment.yolo import YOLOSegmenter

    marker = tmp_path / "ran.txt"
    weights = plant(tmp_path / "yolo.pt", marker)
    with pytest.raises(
        UntrustedCheckpoint, match=r"segmenter\.weights=.*yolo\.pt.*trust_checkpoint"
    ):
        YOLOSegmenter(weights=str(weights)).check()
    assert not marker.exists()


def test_a_real_yolo_checkpoint_loads_without_trust(tmp_path):
    pytest.importorskip("ultralytics")
    from sagonline.segment.yolo import YOLOSegmenter

    model = YOLOSegmenter(model_yaml="yolo11n-seg.yaml").load_model()  # random weights
    model.save(tmp_path / "random.pt")  # a full ultralytics checkpoint (pickled model)
    loaded = YOLOSegmenter(weights=str(tmp_path / "random.pt")).load_model()
    assert type(loaded.model).__name__ == "SegmentationModel"


@pytest.mark.parametrize("option", ["sam3", "pretrained"])
def test_pickled_user_checkpoints_are_refused_by_name(tmp_path, option):
    from sagonline.refine.network import ResNetEncoder, load_imagenet_weights
    from sagonline.scene.io.checkpoints import UntrustedCheckpoint
    from sagonline.segment.sam3_text import SAM3TextSegmenter

    marker = tmp_path / "ran.txt"
    path = plant(tmp_path / "w.pt", marker)
    with pytest.raises(UntrustedCheckpoint, match="arbitrary unpickling") as exc:
        if option == "sam3":
            SAM3TextSegmenter(checkpoint=str(path)).check()
        else:
            load_imagenet_weights(ResNetEncoder("resnet18"), path)
    assert str(path) in str(exc.value) and not marker.exists()
