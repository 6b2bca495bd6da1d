"""SAM 2 video predictor from a local checkpoint (extra: `pip install -e '.[sam2]'`).

The model is built from the config shipped inside the `sam2` package (OmegaConf +
`hydra.utils.instantiate`, not sam2's own Hydra initialisation, which would collide with the
harness's Hydra app), the checkpoint's `model` state dict is loaded, and the rendered frames
are handed to the predictor as a folder of JPEGs. Every prompted object is added on the
prompt frame (clicks and/or box, or its mask with `use_masks`), then propagated forwards and
backwards through the pseudo-temporal video; where objects overlap, the larger logit wins.

Nothing is downloaded: `checkpoint` must be a local file (e.g. sam2.1_hiera_tiny.pt). For
tests, `allow_random_weights=True` builds the same network with random weights.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from sagonline.core.plugins import SEGMENTERS
from sagonline.scene.io.checkpoints import load_user_checkpoint
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import Prompt

VIDEO_OVERRIDES = {
    "model._target_": "sam2.sam2_video_predictor.SAM2VideoPredictor",
    "model.sam_mask_decoder_extra_args.dynamic_multimask_via_stability": True,
    "model.sam_mask_decoder_extra_args.dynamic_multimask_stability_delta": 0.05,
    "model.sam_mask_decoder_extra_args.dynamic_multimask_stability_thresh": 0.98,
    "model.binarize_mask_from_pts_for_mem_enc": True,
    "model.fill_hole_area": 8,
}


def _require_sam2():
    from hydra.core.global_hydra import GlobalHydra

    from sagonline.segment.compat import import_torchvision

    owned = GlobalHydra.instance().is_initialized()
    try:
        import_torchvision()
        import sam2  # initialises Hydra globally when nobody else has
    except ImportError as exc:
        raise RuntimeError(
            "segmenter 'sam2' needs the sam2 package: pip install -e '.[sam2]' "
            "--no-build-isolation (after torch is installed)"
        ) from exc
    if not owned and GlobalHydra.instance().is_initialized():
        GlobalHydra.instance().clear()  # we build from the config file, not through Hydra's
    return Path(sam2.__file__).parent


@dataclass
class SAM2Config:
    """SAM 2's settings (`segmenter=sam2`)."""

    checkpoint: str | None = None
    """REQUIRED: a local checkpoint, e.g. /path/to/sam2.1_hiera_tiny.pt (nothing is downloaded)."""
    config: str = "configs/sam2.1/sam2.1_hiera_t.yaml"
    """The model config inside the sam2 package; it must match the checkpoint."""
    device: str = "cpu"
    """Where the model runs (follows the run's `device`)."""
    image_size: int | None = None
    """The model's input size; None: the config's (1024)."""
    use_masks: bool = False
    """Prompt with the reference mask instead of the clicks."""
    allow_random_weights: bool = False
    """Build the network with random weights when no checkpoint is given (tests only)."""


def package_config(pkg: Path, name: str) -> Path:
    """The model config `name` inside the sam2 package's configs/ folder. A path that leads
    anywhere else (absolute, `..`, a link out) is refused: the config's `_target_`s are
    instantiated, so it must be the package's own file, never one a run folder names."""
    root = (pkg / "configs").resolve()
    path = (pkg / name).resolve()
    if not path.is_relative_to(root) or path.suffix != ".yaml":
        raise ValueError(
            f"segmenter.config={name}: must name a .yaml under the sam2 package's configs/ "
            f"folder ({root}), e.g. configs/sam2.1/sam2.1_hiera_t.yaml"
        )
    if not path.is_file():
        raise FileNotFoundError(f"segmenter.config={name}: not in the sam2 package ({root})")
    return path


def check_targets(node, where: str = "model") -> None:
    """Refuse any `_target_` in a model config that is not a class of the sam2 package: only
    sam2's own classes are built from the config, whatever the file says."""
    from omegaconf import DictConfig, ListConfig

    if isinstance(node, DictConfig):
        target = node.get("_target_")
        if target is not None and not str(target).startswith("sam2."):
            raise ValueError(f"sam2 model config: {where}._target_={target!r} is not sam2's own")
        for key in node:
            check_targets(node[key], f"{where}.{key}")
    elif isinstance(node, ListConfig):
        for i, item in enumerate(node):
            check_targets(item, f"{where}[{i}]")


@SEGMENTERS.register("sam2", SAM2Config)
class SAM2VideoSegmenter(VideoSegmenter):
    """SAM 2 video predictor from a local checkpoint (extra: .[sam2])."""

    name = "sam2"

    def __init__(
        self,
        checkpoint: str | None = None,
        config: str = "configs/sam2.1/sam2.1_hiera_t.yaml",
        device: str = "cpu",
        image_size: int | None = None,
        use_masks: bool = False,
        allow_random_weights: bool = False,
    ):
        if checkpoint is None and not allow_random_weights:
            raise ValueError(
                "segmenter 'sam2' needs a local checkpoint: set "
                "segmenter.checkpoint=/path/to/sam2.1_hiera_tiny.pt (nothing is "
                "downloaded). SAM 2 Hiera-tiny as ONNX files, prompted view by view: "
                "segmenter=sam2_tiny, after `make weights`"
            )
        if checkpoint is not None and not Path(checkpoint).is_file():
            raise FileNotFoundError(f"segmenter.checkpoint={checkpoint}: no such file")
        self.checkpoint, self.config, self.device = checkpoint, config, device
        self.image_size, self.use_masks = image_size, use_masks
        self.reads = ("masks", "clicks", "boxes") if use_masks else ("clicks", "boxes")
        self._predictor = None

    def weight_files(self) -> list[str]:
        return [self.checkpoint] if self.checkpoint else []

    def check(self) -> None:
        """Build the model now (loading the checkpoint), so a bad file stops the run before
        anything is rendered."""
        try:
            self.build()
        except (ValueError, RuntimeError, OSError) as exc:
            raise ValueError(str(exc)) from exc

    def build(self):
        from hydra.utils import instantiate
        from omegaconf import OmegaConf

        pkg = _require_sam2()
        cfg_path = package_config(pkg, self.config)
        cfg = OmegaConf.load(cfg_path)
        overrides = dict(VIDEO_OVERRIDES)
        try:  # hole filling needs sam2's compiled extension; without it sam2 warns and skips
            from sam2 import _C  # noqa: F401
        except ImportError:
            overrides["model.fill_hole_area"] = 0
        if self.image_size is not None:
            overrides["model.image_size"] = int(self.image_size)
        for key, value in overrides.items():
            OmegaConf.update(cfg, key, value, force_add=True)
        OmegaConf.resolve(cfg)
        check_targets(cfg.model)
        model = instantiate(cfg.model, _recursive_=True)
        if self.checkpoint is not None:
            # sam2 itself loads with weights_only=True: a pickled object is refused either way
            state = load_user_checkpoint(self.checkpoint, "segmenter.checkpoint")
            state = state.get("model", state) if isinstance(state, dict) else state
            if not isinstance(state, dict):
                raise ValueError(
                    f"segmenter.checkpoint={self.checkpoint}: holds a {type(state).__name__}, "
                    "not a state dict (or a dict with a 'model' state dict)"
                )
            try:
                missing, unexpected = model.load_state_dict(state, strict=False)
            except RuntimeError as exc:  # shape mismatches raise even when not strict
                raise RuntimeError(
                    f"segmenter.checkpoint={self.checkpoint} does not fit {self.config}: {exc}"
                ) from exc
            if missing or unexpected:
                raise RuntimeError(
                    f"segmenter.checkpoint={self.checkpoint} does not fit "
                    f"{self.config}: {len(missing)} missing and "
                    f"{len(unexpected)} unexpected keys (e.g. "
                    f"{(missing or unexpected)[:3]})"
                )
        self._predictor = model.to(self.device).eval()
        return self._predictor

    def _segment(self, frames, prompt: Prompt, ground_truth):
        import cv2

        if not prompt.objects:
            raise ValueError("segmenter 'sam2' needs clicks, boxes or masks on the prompt frame")
        predictor = self._predictor or self.build()
        h, w = frames[0].shape[:2]
        logits = np.full((len(frames), len(prompt.objects), h, w), -np.inf, np.float32)
        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp, torch.inference_mode():
            for i, f in enumerate(frames):
                cv2.imwrite(
                    str(Path(tmp) / f"{i:05d}.jpg"), f[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95]
                )
            state = predictor.init_state(
                video_path=tmp, offload_video_to_cpu=True, offload_state_to_cpu=True
            )
            for obj in prompt.objects:
                if obj.mask is not None and (self.use_masks or obj.points is None):
                    predictor.add_new_mask(
                        state,
                        frame_idx=prompt.frame,
                        obj_id=obj.label,
                        mask=np.asarray(obj.mask, bool),
                    )
                else:
                    predictor.add_new_points_or_box(
                        state,
                        frame_idx=prompt.frame,
                        obj_id=obj.label,
                        points=None if obj.points is None else np.asarray(obj.points, np.float32),
                        labels=None
                        if obj.point_labels is None
                        else np.asarray(obj.point_labels, np.int32),
                        box=None if obj.box is None else np.asarray(obj.box, np.float32),
                    )
            order = {o.label: k for k, o in enumerate(prompt.objects)}
            for reverse in (False, True):
                for f, obj_ids, masks in predictor.propagate_in_video(
                    state, start_frame_idx=prompt.frame, reverse=reverse
                ):
                    for oid, m in zip(obj_ids, masks, strict=True):
                        logits[f, order[int(oid)]] = m[0].float().cpu().numpy()
        labels_of = np.array([o.label for o in prompt.objects])
        out = []
        for f in range(len(frames)):
            best = logits[f].argmax(0)
            fg = logits[f].max(0) > 0
            out.append(np.where(fg, labels_of[best], 0))
        per_frame = (time.perf_counter() - start) / len(frames)
        return out, [per_frame] * len(frames)
