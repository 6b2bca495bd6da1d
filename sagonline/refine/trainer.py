"""Online distillation of the refinement student, in a background thread, resumable.

Inputs per trajectory view: the rendered RGB frame and the coarse label render of the fused
Stage I labels (one-hot, lightly smoothed); target: the 2D segmenter's mask of that frame (the
teacher). Loss: pixel-wise cross-entropy. Training stops when the smoothed loss has not improved
by `min_delta` for `patience` steps after a warm-up of `patience` steps ("converged":
`Plateau`), at `max_steps` ("steps"), or, only when one is set, at `time_budget_s` seconds of
training ("time_budget": then the result depends on how busy the machine was). The same seed and
settings give the same weights on a quiet and on a loaded machine, with the same number of torch
threads (another count sums in another order: another draw). With `ema_span`, the student
answers from a moving average of its weights (`WeightAverage`), which the training itself never
reads; `scored_spans` keeps more averages, to compare. A checkpoint (model, optimiser, the
averages, step, loss, status) is written atomically every `checkpoint_every` steps and at the
end; a new trainer given the same path resumes from it, drawing the batches that one training
run straight through draws (so it ends with the same weights), and one that finds a finished
checkpoint does not train again.
"""

from __future__ import annotations

import threading
import time
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from sagonline.core import store
from sagonline.core.settings import check_settings
from sagonline.core.tensors import tensor_view
from sagonline.refine.network import ARCHS, DualBranchRefiner
from sagonline.refine.plateau import Plateau
from sagonline.refine.weight_average import WeightAverage

STOPS = ("converged", "steps", "time_budget")  # why a training stopped


@dataclass
class RefineConfig:
    encoder: str = "resnet18"
    """The image branch: resnet18 (CPU-friendly), resnet34, or resnet50 (the paper's)."""
    pretrained: str | None = None
    """A local torchvision-format ImageNet state dict (loaded weights_only); None: random."""
    max_steps: int = 400
    """Training stops here ("steps") unless it converged before."""
    time_budget_s: float | None = None
    """Seconds of training ("time_budget"); None: bounded by steps alone (reproducible)."""
    batch_size: int = 8
    """Views per step."""
    crop: int = 128
    """Random crops of this size (full frames when larger)."""
    decoder_width: int = 32
    """Channels of the U-Net decoder."""
    lr: float = 1e-3
    """Adam's learning rate."""
    patience: int = 60
    """Steps without a gain of min_delta in the smoothed loss: "converged"."""
    min_delta: float = 1e-3
    """The smoothed loss's least gain that counts."""
    checkpoint_every: int = 25
    """Steps between checkpoints (a resumed training starts from the last)."""
    curve_every: int = 0
    """Every this many steps (and at the first and the last), the student as it is then is
    scored at the eval views (metrics.json `extra.refine.curve`); 0: never. The weights are
    those of a training without it; its scoring pauses the training."""
    ema_span: int = 60
    """The student answers from an exponential moving average of its weights (and norm
    statistics) over about this many steps (each step weighs 2 / (span + 1); the plain mean of
    all steps until that is smaller); 0: from its weights as they are (the default until the
    average was measured, docs/real_captures.md). The training is the same either way. 60:
    the plateau rule's patience, chosen before any capture was scored."""
    scored_spans: list[int] = field(default_factory=list)
    """Spans of further weight averages kept beside the answers' (each costs one more update a
    step), to compare: where the student stopped, the eval views are scored with each, with
    the answers' and with the trained weights (metrics.json `extra.refine.span_miou`, by span;
    0: the trained weights). The answers stay the `ema_span` average's. For choosing
    `ema_span` (`bench.runners.student --spans`)."""
    coarse_smoothing: float = 0.1
    """Label smoothing of the coarse render fed to the mask branch."""
    seed: int = 0
    """Seeds the batches and crops."""
    device: str = "cpu"
    """Where the student trains."""

    def __post_init__(self) -> None:
        budget = self.time_budget_s
        check_settings(
            "refine",
            encoder=(self.encoder in ARCHS, self.encoder, f"one of {sorted(ARCHS)}"),
            max_steps=(self.max_steps >= 1, self.max_steps, ">= 1"),
            time_budget_s=(budget is None or budget >= 0, budget, ">= 0 seconds, or null"),
            batch_size=(self.batch_size >= 1, self.batch_size, ">= 1"),
            crop=(self.crop >= 16, self.crop, ">= 16 pixels"),
            decoder_width=(self.decoder_width >= 1, self.decoder_width, ">= 1"),
            lr=(self.lr > 0, self.lr, "> 0"),
            patience=(self.patience >= 1, self.patience, ">= 1"),
            min_delta=(self.min_delta >= 0, self.min_delta, ">= 0"),
            checkpoint_every=(self.checkpoint_every >= 1, self.checkpoint_every, ">= 1"),
            curve_every=(self.curve_every >= 0, self.curve_every, ">= 0 (0: no curve)"),
            ema_span=(self.ema_span >= 0, self.ema_span, ">= 0 steps (0: no average)"),
            scored_spans=(
                all(s >= 1 for s in self.scored_spans)
                and len(set(self.scored_spans)) == len(self.scored_spans),
                self.scored_spans,
                "distinct spans >= 1 step",
            ),
            coarse_smoothing=(
                0 <= self.coarse_smoothing < 1,
                self.coarse_smoothing,
                "in [0, 1)",
            ),
        )


def coarse_input(
    labels: np.ndarray | torch.Tensor,  # [H, W] coarse label map
    num_classes: int,
    smoothing: float = 0.1,
) -> torch.Tensor:  # [C, H, W] smoothed one-hot
    """(H, W) coarse label map -> (C, H, W) smoothed one-hot, the student's mask input."""
    lab = tensor_view(labels if isinstance(labels, torch.Tensor) else np.asarray(labels)).long()
    onehot = F.one_hot(lab, num_classes).permute(2, 0, 1).float()
    return onehot * (1 - smoothing) + smoothing / num_classes


def rgb_input(
    frame: np.ndarray,
) -> torch.Tensor:  # [3, H, W] in [0, 1]
    """(H, W, 3) uint8 -> (3, H, W) float in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(frame)).permute(2, 0, 1).float() / 255.0


class RefinementTrainer:
    """Trains a `DualBranchRefiner` on (frames, coarse, teacher) in the background."""

    def __init__(
        self,
        cfg: RefineConfig,
        num_classes: int,
        frames: list[np.ndarray],
        coarse: list[np.ndarray],
        teacher: list[np.ndarray],
        checkpoint: str | Path | None = None,
    ):
        if not (len(frames) == len(coarse) == len(teacher)) or not frames:
            raise ValueError("refinement needs as many frames, coarse renders and teacher masks")
        self.cfg, self.num_classes = cfg, num_classes
        self.checkpoint = Path(checkpoint) if checkpoint is not None else None
        torch.manual_seed(cfg.seed)
        self.model = DualBranchRefiner(
            num_classes, cfg.encoder, cfg.pretrained, decoder_width=cfg.decoder_width
        ).to(cfg.device)
        self.optim = torch.optim.Adam(self.model.parameters(), lr=cfg.lr)
        self.averages = {  # span -> the weights' average over it: the answers' and the scored
            span: WeightAverage(self.model, span)
            for span in dict.fromkeys([cfg.ema_span, *cfg.scored_spans])
            if span
        }
        self.rgb = torch.stack([rgb_input(f) for f in frames])
        self.coarse = torch.stack(
            [coarse_input(c, num_classes, cfg.coarse_smoothing) for c in coarse]
        )
        self.teacher = torch.stack(
            [torch.as_tensor(np.asarray(t), dtype=torch.long) for t in teacher]
        )
        if int(self.teacher.max()) >= num_classes:
            raise ValueError(
                f"teacher masks hold label {int(self.teacher.max())} but the "
                f"student has {num_classes} classes"
            )
        self.step = 0
        self.plateau = Plateau(cfg.patience, cfg.min_delta, warmup=cfg.patience)
        self.status, self.train_s, self.losses = "idle", 0.0, []
        self.curve: list[dict] = []  # {step, loss, miou[, miou_trained]} every `curve_every`
        # the curve's scorer: the eval views' mIoU of the weights `predict`'s `span` names
        self.score_now: Callable[[int | None], float | None] | None = None
        self.done = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._resume()

    @property
    def average(self) -> WeightAverage | None:
        """The average the student answers from (`ema_span`; None: 0)."""
        return self.averages.get(self.cfg.ema_span)

    @property
    def span_averages(self) -> dict[int, WeightAverage]:
        """The scored spans' averages but the answers'."""
        return {s: a for s, a in self.averages.items() if s != self.cfg.ema_span}

    # --- checkpoints --------------------------------------------------------------------------
    def _resume(self) -> None:
        if self.checkpoint is None:
            return
        state = store.load_or_discard(self.checkpoint, "student checkpoint")
        if state is None:
            return
        if not isinstance(state, dict) or state.get("file") != self.checkpoint.name:
            # a checkpoint copied or renamed from another key: never resumed from
            warnings.warn(
                f"student checkpoint {self.checkpoint} was written as "
                f"{state.get('file') if isinstance(state, dict) else None!r}; removed and "
                "trained again",
                stacklevel=2,
            )
            self.checkpoint.unlink(missing_ok=True)
            return
        same = (state.get("config"), state.get("classes")) == (asdict(self.cfg), self.num_classes)
        if not same or "averages" not in state:  # another setting, or averages kept otherwise:
            return  # start over (the old file is replaced at the first save)
        self.model.load_state_dict(state["model"])
        self.optim.load_state_dict(state["optim"])
        for span, average in self.averages.items():
            average.load_state_dict(state["averages"][span])
        self.step, self.train_s = state["step"], state["train_s"]
        self.losses, self.status = state["losses"], state["status"]
        self.curve = state.get("curve", [])
        for loss in self.losses:  # the plateau rule replayed: the same state as before
            self.plateau.add(loss)
        if self.status in STOPS:
            self.done.set()

    def save(self) -> None:
        if self.checkpoint is None:
            return
        with self._lock:
            state = {
                "model": self.model.state_dict(),
                "optim": self.optim.state_dict(),
                "averages": {span: a.state_dict() for span, a in self.averages.items()},
                "step": self.step,
                "best_step": self.plateau.best_step,
                "train_s": self.train_s,
                "losses": self.losses,
                "status": self.status,
                "curve": self.curve,
                "config": asdict(self.cfg),
                "classes": self.num_classes,
                "file": self.checkpoint.name,  # its stage and key: never resumed under another
            }
            try:
                store.save(self.checkpoint, state)
            except OSError as exc:  # the cache folder cannot be written: train on without it
                warnings.warn(
                    f"student checkpoint {self.checkpoint} cannot be written "
                    f"({exc.strerror or exc}); training goes on without checkpoints",
                    stacklevel=2,
                )
                self.checkpoint = None

    # --- training -----------------------------------------------------------------------------
    def start(self) -> RefinementTrainer:
        """Train in a background thread (returns at once; `done` is set when it stops)."""
        if self.done.is_set():
            return self
        self._thread = threading.Thread(target=self.run, name="refinement", daemon=True)
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        return self.done.wait(timeout)

    def run(self) -> str:
        cfg = self.cfg
        self.status = "training"
        gen = self._batch_draws()
        start, session_start = time.perf_counter(), self.train_s
        if self.step == 0:
            self._curve_point()
        while True:
            if self.step >= cfg.max_steps:
                self.status = "steps"
                break
            if cfg.time_budget_s is not None and self.train_s >= cfg.time_budget_s:
                self.status = "time_budget"
                break
            if self.plateau.converged:
                self.status = "converged"
                break
            value = self.train_step(*self._batch(gen))
            self.losses.append(value)
            self.plateau.add(value)
            self.step += 1
            self.train_s = session_start + time.perf_counter() - start
            if cfg.curve_every and self.step % cfg.curve_every == 0:
                self._curve_point()
                start = time.perf_counter() - (self.train_s - session_start)  # not training
            if self.step % cfg.checkpoint_every == 0:
                self.save()
        if not self.curve or self.curve[-1]["step"] != self.step:
            self._curve_point()  # where it stopped
        self.save()
        self.done.set()
        return self.status

    def train_step(
        self,
        rgb: torch.Tensor,  # [B, 3, h, w] in [0, 1]
        coarse: torch.Tensor,  # [B, C, h, w] smoothed one-hot
        teacher: torch.Tensor,  # [B, h, w] labels
    ) -> float:  # the batch's loss
        """One optimiser step on a batch, the weights' averages updated after it."""
        device = self.cfg.device
        with self._lock:
            self.model.train()
            logits = self.model(rgb.to(device), coarse.to(device))
            loss = F.cross_entropy(logits, teacher.to(device))
            self.optim.zero_grad(set_to_none=True)
            loss.backward()
            self.optim.step()
            for average in self.averages.values():
                average.update(self.model)
        return loss.item()

    def _curve_point(self) -> None:
        """The student as it is now, scored (`score_now`) into the curve; with `curve_every`
        set and a scorer given only. With `ema_span`, `miou` scores its answers (the average)
        and `miou_trained` its trained weights."""
        if not self.cfg.curve_every or self.score_now is None:
            return
        point = {"step": self.step, "loss": self.plateau.ema, "miou": self.score_now(None)}
        if self.average is not None:
            point["miou_trained"] = self.score_now(0)
        self.curve.append(point)

    def _batch_draws(self) -> torch.Generator:
        """The batches' draw at the current step: seeded by `seed` and advanced past the
        steps already trained, so a training resumed from a checkpoint draws the batches that
        one run straight through draws."""
        gen = torch.Generator().manual_seed(self.cfg.seed)
        for _ in range(self.step):
            self._picks(gen)
        return gen

    def _picks(self, gen: torch.Generator) -> tuple[list[tuple[int, int, int]], int, int]:
        """One batch's (view, top, left) crops drawn from `gen`, and the crops' height and
        width."""
        n = min(self.cfg.batch_size, len(self.rgb))
        idx = torch.randint(len(self.rgb), (n,), generator=gen)
        H, W = self.rgb.shape[-2:]
        ch, cw = min(self.cfg.crop, H), min(self.cfg.crop, W)
        ys = torch.randint(H - ch + 1, (n,), generator=gen).tolist()
        xs = torch.randint(W - cw + 1, (n,), generator=gen).tolist()
        return list(zip(idx.tolist(), ys, xs, strict=True)), ch, cw

    def _batch(self, gen: torch.Generator):
        """A batch of random views, each cropped at a random place to `crop` px."""
        picks, ch, cw = self._picks(gen)

        def crop(t: torch.Tensor) -> torch.Tensor:
            return torch.stack([t[i, ..., y : y + ch, x : x + cw] for i, y, x in picks])

        return crop(self.rgb), crop(self.coarse), crop(self.teacher)

    # --- answering ----------------------------------------------------------------------------
    @torch.no_grad()
    def predict(
        self,
        frame: np.ndarray,  # [H, W, 3] uint8 RGB render
        coarse: np.ndarray,  # [H, W] coarse label render
        size: tuple[int, int] | None = None,  # (H', W') to answer at; None: (H, W)
        span: int | None = None,  # None: the answers' weights; 0: trained; k: k steps' average
    ) -> np.ndarray:  # [H', W'] labels
        """Labels for one view from its RGB render and coarse label render; at another `size`
        (the scored label render's, `label_render.size=truth`) the student's class scores are
        drawn up bilinearly before the argmax, so its outline is not the render's pixel
        grid blown up. With `ema_span`, from the weights' average (before the first step: the
        weights as they are); another `span`: the trained weights (0) or the average over that
        many steps (`scored_spans`)."""
        with self._lock:
            model = self.weights(self.cfg.ema_span if span is None else span)
            model.eval()
            logits = model(
                rgb_input(frame)[None].to(self.cfg.device),
                coarse_input(coarse, self.num_classes, self.cfg.coarse_smoothing)[None].to(
                    self.cfg.device
                ),
            )
            if size is not None and tuple(size) != tuple(logits.shape[-2:]):
                logits = F.interpolate(logits, size=tuple(size), mode="bilinear")
        return logits[0].argmax(0).cpu().numpy()

    def weights(self, span: int) -> torch.nn.Module:
        """The trained weights (`span` 0), or their average over `span` steps (`ema_span` or
        one of `scored_spans`; before the first step, the weights as they are)."""
        if span == 0:
            return self.model
        average = self.averages.get(span)
        if average is None:
            raise ValueError(
                f"no average over {span} steps is kept (refine.ema_span={self.cfg.ema_span}, "
                f"refine.scored_spans={self.cfg.scored_spans})"
            )
        return average.model if average.steps else self.model
