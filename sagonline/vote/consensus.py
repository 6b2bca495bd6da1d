"""Lift 2D label masks to one discrete label per Gaussian.

The vote walks, for every pixel of every selected mask, its Gaussians front to back and adds
the pairs its method's rule lets vote to one histogram per Gaussian (`render.vote.vote_into`);
the method then turns the histogram into labels. The methods (`vote.methods`: rgc, the paper's
Rasterization-aware Geometric Consensus, and the flashsplat and weighted_mean baselines) are
plug-ins of `plugins.VOTE_RULES`, each with its own typed settings; `VoteConfig` (in
`vote.settings`, without PyTorch) holds them under flat names (`consensus.eps`, ...) and
refuses a setting its method does not read when it is built (`consensus=flashsplat
consensus.delta=1.5` stops, naming delta).

Labels: (N,) int64, -1 unlabelled, 0 background, 1.. the objects, from the vote to every
output (`VoteResult.labels`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from sagonline.core.store import stored
from sagonline.render.vote import vote_into
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.vote.body import extents, keep_bodies
from sagonline.vote.fill import fill_from_neighbours
from sagonline.vote.masks import MaskError, check_mask
from sagonline.vote.settings import VoteConfig


@stored
@dataclass
class VoteResult:
    """labels: (N,) int64, -1 unlabelled, 0 background, 1.. the objects (the one encoding of
    every output and label render); histogram: (N, K) float32 votes or weights; frames: the
    trajectory indices of the masks that voted, in the order they voted; stats: fractions,
    counts and timings."""

    labels: torch.Tensor
    histogram: torch.Tensor
    frames: list[int]
    stats: dict = field(default_factory=dict)


def select_frames(num_frames: int, cfg: VoteConfig) -> list[int]:
    """Indices of the masks that vote: every `stride`-th, then `num_masks` of those."""
    candidates = list(range(0, num_frames, cfg.stride))
    n = cfg.num_masks
    if n is None or n >= len(candidates):
        return candidates
    if n <= 0:
        raise ValueError(f"num_masks must be positive, got {n}")
    if cfg.selection == "first":
        return candidates[:n]
    if cfg.selection == "random":
        rng = np.random.default_rng(cfg.seed)
        return sorted(rng.choice(candidates, size=n, replace=False).tolist())
    picks = np.linspace(0, len(candidates) - 1, n).round().astype(int)
    return [candidates[i] for i in sorted(set(picks.tolist()))]


class VoteAccumulator:
    """The running (N, K) vote histogram of one method: views are added one by one by the vote
    op (`render.vote.vote_into`), labels are read off at any time (`labels`), the result with
    its statistics at the end (`result`). means: (N, 3) the Gaussians' centres, needed only by
    the fill and the body rule (`consensus.fill`, `consensus.body`); extents: (N,) their largest
    scales, needed by the body rule (`vote.body.extents`)."""

    def __init__(
        self,
        num_gaussians: int,
        num_labels: int,
        cfg: VoteConfig,
        device: torch.device | str = "cpu",
        means: torch.Tensor | None = None,
        extents: np.ndarray | None = None,
    ):
        self.cfg, self.k, self.rule, self.means = cfg, num_labels, cfg.rule, means
        self.extents = extents
        self.hist = torch.zeros(num_gaussians, num_labels, dtype=torch.float64, device=device)
        self.frames: list[int] = []
        self.pairs = 0  # (pixel, Gaussian) pairs that voted
        self.seconds = 0.0  # spent in the vote op and reading labels off
        self.dropped: torch.Tensor | None = None  # [N] bool, off their object's body
        self._read: tuple | None = None  # (histogram, its version, cfg, [N] `labels` of them)

    def grow(self, num_labels: int) -> None:
        """Make room for labels up to num_labels - 1 (a segmenter may name more objects than
        the prompt did)."""
        if num_labels > self.k:
            extra = self.hist.new_zeros(self.hist.shape[0], num_labels - self.k)
            self.hist = torch.cat([self.hist, extra], dim=1).contiguous()
            self.k = num_labels
            self._read = None

    def add_view(
        self,
        gaussians: Gaussians,
        camera: Camera,
        mask,
        backend: str,
        where: str = "mask",
        frame: int | None = None,
    ) -> int:
        """Vote one view's (H, W) label map (`where` names it in errors; `frame`: its index in
        the trajectory); returns the pairs that voted."""
        start = time.perf_counter()
        labels = check_mask(mask, camera, self.k, where).view(camera.height, camera.width)
        self._read = None  # the histogram changes from here (also where the vote fails)
        cast = vote_into(gaussians, camera, labels, self.rule, self.hist, backend=backend)
        self.pairs += cast
        self.frames.append(len(self.frames) if frame is None else frame)
        self.seconds += time.perf_counter() - start
        return cast

    def labels(self) -> torch.Tensor:  # [N] int64, -1 unlabelled
        """The labels of the histogram so far: the method's rule, then the config's fill (the
        body rule, `consensus.body`, applies to the final labels, `result`). Decided once per
        histogram: until a view votes, the labels grow, or the histogram or the settings are
        changed, every call returns the same tensor, which callers must not change in place
        (Stage I reads them after a view's vote and again for the next view's advice)."""
        read = self._read
        if read is None or read[0] is not self.hist or read[1:3] != (self.hist._version, self.cfg):
            read = (self.hist, self.hist._version, self.cfg, self._decide(final=False)[0])
            self._read = read
        return read[3]

    def _decide(self, final: bool = True) -> tuple[torch.Tensor, torch.Tensor]:  # [N], [N] filled
        start = time.perf_counter()
        labels = decide(self.hist, self.cfg)
        filled = torch.zeros_like(labels, dtype=torch.bool)
        if (self.cfg.fill or self.cfg.body) and self.means is None:
            raise ValueError("consensus.fill and consensus.body need the Gaussians' centres")
        if self.cfg.body and self.extents is None:
            raise ValueError("consensus.body needs the Gaussians' extents (extents=)")
        if self.cfg.fill:
            labels, filled = fill_from_neighbours(self.means, labels, self.cfg.fill)
        if self.cfg.body and final:
            labels, self.dropped = keep_bodies(self.means, self.extents, labels)
        self.seconds += time.perf_counter() - start
        return labels, filled

    def result(self) -> VoteResult:
        """The labels, the histogram (float32), the frames that voted and the statistics."""
        labels, filled = self._decide()
        total = self.hist.sum(1)
        voted = total > 0
        labelled = labels >= 0
        off = self.dropped if self.dropped is not None else torch.zeros_like(labelled)
        n = len(self.frames)
        stats = {
            "fraction_filled": float(filled.float().mean()) if len(labels) else 0.0,
            "fraction_off_body": float(off.float().mean()) if len(labels) else 0.0,
            "num_masks": n,
            "fraction_labelled": float(labelled.float().mean()) if len(labels) else 0.0,
            "fraction_voted": float(voted.float().mean()) if len(labels) else 0.0,
            "fraction_ambiguous": float((voted & ~labelled & ~filled & ~off).float().mean())
            if len(labels)
            else 0.0,
            "votes_per_gaussian_mean": float(total[voted].mean()) if voted.any() else 0.0,
            "votes_per_gaussian_median": float(total[voted].median()) if voted.any() else 0.0,
            "votes_cast": self.pairs,
            "aggregation_s": self.seconds,
            "ms_per_mask": 1000.0 * self.seconds / max(n, 1),
        }
        return VoteResult(labels, self.hist.float(), list(self.frames), stats)


def decide(
    hist: torch.Tensor,  # [N, K] votes or blend weights
    cfg: VoteConfig,
) -> torch.Tensor:  # [N] int64, -1 unlabelled
    """Histogram -> labels by the method's rule (`vote.methods`): -1 where it leaves a Gaussian
    unlabelled."""
    labels, labelled = cfg.method_rule().decide(hist, cfg.settings())
    return torch.where(labelled, labels.long(), torch.full_like(labels.long(), -1))


def consensus_vote(
    gaussians: Gaussians,
    cameras: Sequence[Camera],
    masks: Sequence,
    num_labels: int,
    cfg: VoteConfig | None = None,
    *,
    backend: str = "auto",
) -> VoteResult:
    """Vote every selected (camera, mask) pair into one label per Gaussian, in one call (the
    pipeline streams the same accumulator view by view: `pipeline.stage_one.StageOne`).

    cameras: T views; masks: T label maps (H, W) with ids in [0, num_labels), one per view.
    """
    cfg = cfg or VoteConfig()
    if len(cameras) != len(masks):
        raise MaskError(f"{len(cameras)} cameras but {len(masks)} masks")
    acc = VoteAccumulator(
        len(gaussians), num_labels, cfg, gaussians.device, gaussians.means, extents(gaussians)
    )
    for f in select_frames(len(cameras), cfg):
        acc.add_view(gaussians, cameras[f], masks[f], backend, f"mask of frame {f}", frame=f)
    return acc.result()
