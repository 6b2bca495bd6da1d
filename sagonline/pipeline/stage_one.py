"""Stage I as one engine that every front end streams from: render the trajectory, segment it
mask by mask, vote each mask as it comes, publish labels per Gaussian.

Shaped like the video predictors the field knows (SAM 2's `init_state` /
`add_new_points_or_box` / `propagate_in_video`):

    engine = StageOne(StageOneConfig(gaussians, cameras, segmenter, VoteConfig()))
    engine.add_prompt(0, points=[(412, 230)], name="chair")     # clicks, a box, a mask or text
    for event in engine.stream():                                # FrameRendered, MaskReady,
        ...                                                      # ViewVoted, LabelsUpdated
    engine.result().labels                                       # (N,) int64, -1 unlabelled

`stream()` can be stopped (`stop()`, from any thread: after the event in hand) and resumed (call
it again); a new prompt starts the masks and the vote again on the same frames. `run()` drains
the stream and returns the stages' outputs: the batch evaluation (`pipeline.scene.run_scene`),
`sagonline segment` (`pipeline.segment.segment_scene`), the viewer's session, `sagonline export`
and the diagnosis's counterfactual vote all consume it, and none of them owns a frame loop or a
vote of its own. Which mask a view votes with is the engine's mask policy: the segmenter's own
stream, or consensus feedback (`vote.feedback.FeedbackPolicy`), under one frame selection
(`VoteConfig.num_masks`, `stride`, `selection`).

Each stage's output is cached under the key of its inputs (`stages.py`): frames, masks and vote
found in the cache are streamed from it (their events say `cached=True`); what is computed is
saved once its stage is complete, so an interrupted run resumes from the last finished stage.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from sagonline.core.errors import PromptError
from sagonline.pipeline.events import (
    Event,
    FrameRendered,
    LabelsUpdated,
    MaskReady,
    StageOneOutput,
    ViewVoted,
)
from sagonline.pipeline.graph import Output, StageCache, StageRun
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stages import (
    FRAMES,
    MASKS,
    VOTE,
    Frames,
    FramesInputs,
    MasksInputs,
    SegmenterRun,
    stage_keys,
)
from sagonline.render.api import render, to_uint8
from sagonline.render.backends import implementation_digest, plan_backends
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.base import SegmentationResult, label_map
from sagonline.segment.prompts import Prompt, add_to_prompt
from sagonline.vote.body import extents
from sagonline.vote.consensus import VoteAccumulator, VoteConfig, VoteResult, select_frames
from sagonline.vote.feedback import FeedbackPolicy, FusedRender


@dataclass
class StageOneConfig:
    """Everything Stage I reads. gaussians: the scene (moved to `settings.device`); cameras: the
    trajectory, T views in video order; segmenter: the plug-in with what its masks depend on;
    vote: the rule and which frames vote; num_labels: the labels the caller knows of (the
    masks may add more); trajectory_gt: T (H, W) label maps, read by the oracle only; cache:
    where stages are cached (None: nowhere); publish_every: a LabelsUpdated event after the
    first voted view and every that many (None: only at the end); keep_depth: keep each
    rendered frame's opacity and depth (a viewer picks clicks with them); rendered: another
    Stage I's frames, taken where their key is these inputs' (no render, no cache read)."""

    gaussians: Gaussians
    cameras: list[Camera]
    segmenter: SegmenterRun
    vote: VoteConfig = field(default_factory=VoteConfig)
    settings: PipelineSettings = field(default_factory=PipelineSettings)
    num_labels: int = 1
    trajectory_gt: list[np.ndarray] | None = None
    cache: StageCache | None = None
    publish_every: int | None = None
    keep_depth: bool = False
    rendered: Output[Frames] | None = None


# --- the engine ---------------------------------------------------------------------------


class StageOne:
    """Stage I on one scene (see the module docstring)."""

    def __init__(self, config: StageOneConfig, prompt: Prompt | None = None):
        c = self.config = config
        if not c.cameras:
            raise PromptError("no views to segment")
        if c.publish_every is not None and c.publish_every < 1:
            raise ValueError(f"publish_every {c.publish_every}: must be at least 1, or None")
        self.plan = plan_backends(
            c.settings.renderer.backend, c.settings.renderer.vote_backend, c.settings.device
        )
        self.device = torch.device(self.plan.device).type
        self.gaussians = c.gaussians.to(self.plan.device)
        self.cameras = [cam.to(self.plan.device) for cam in c.cameras]
        self.cache = c.cache or StageCache(None)
        self.voting = select_frames(len(self.cameras), c.vote)
        self.frames: list[np.ndarray] | None = None
        self.alphas: list[np.ndarray] = []
        self.depths: list[np.ndarray] = []
        self.runs: dict[str, StageRun] = {}
        self._frames_out: Output[Frames] | None = None
        self._stop = threading.Event()
        self._prompt = prompt or Prompt()
        self._reset()

    # --- prompts ------------------------------------------------------------------------------

    @property
    def prompt(self) -> Prompt:
        return self._prompt

    def set_prompt(self, prompt: Prompt) -> None:
        """Replace the prompt; the masks and the vote start again on the same frames."""
        if not 0 <= prompt.frame < len(self.cameras):
            raise PromptError(
                f"prompt frame {prompt.frame} is outside the {len(self.cameras)} views"
            )
        self._prompt = prompt
        self._reset()

    def add_prompt(
        self,
        frame: int,
        *,
        points=None,  # [P, 2] x, y pixels of the frame at its render size
        point_labels=None,  # [P] 1 positive, 0 negative (default: all positive)
        box=None,  # [4] x0, y0, x1, y1
        mask=None,  # [H, W] bool
        text: str | None = None,
        obj_id: int | None = None,
        name: str | None = None,
    ) -> int:
        """Add clicks, a box, a mask or a text for one object on `frame` (any view; all of a
        prompt's objects are on one view: the segmenters take one) and return its label
        (`segment.prompts.add_to_prompt`). The masks and the vote start again on the same
        frames."""
        if not 0 <= frame < len(self.cameras):
            raise PromptError(f"view {frame} is out of range: there are {len(self.cameras)} views")
        prompt, label = add_to_prompt(
            self._prompt,
            frame,
            points=points,
            point_labels=point_labels,
            box=box,
            mask=mask,
            text=text,
            obj_id=obj_id,
            name=name,
        )
        self.set_prompt(prompt)
        return label

    def configure(self, *, segmenter: SegmenterRun | None = None, vote: VoteConfig | None = None):
        """Another segmenter or other vote settings (the frame selection with them); the masks
        and the vote start again on the same frames."""
        if segmenter is not None:
            self.config = replace(self.config, segmenter=segmenter)
        if vote is not None:
            self.config = replace(self.config, vote=vote)
            self.voting = select_frames(len(self.cameras), vote)
        self._reset()

    # --- the stream -------------------------------------------------------------------------

    def stream(self) -> Iterator[Event]:
        """The events from where the last stream stopped (or the start) to the end."""
        self._stop.clear()
        if self._events is None:
            self._events = self._all_events()
        for event in self._events:
            yield event
            if self._stop.is_set():
                return

    def stop(self) -> None:
        """Stop the stream in hand after its current event (from any thread)."""
        self._stop.set()

    def run(self) -> StageOneOutput:
        """Drain the stream; the stages' outputs."""
        for _ in self.stream():
            pass
        return self.result()

    def render(self) -> list[np.ndarray]:
        """Render (or read from the cache) every frame now; the RGB frames."""
        for _ in self._frame_events():
            pass
        return self.frames

    @property
    def done(self) -> bool:
        return self._out is not None

    @property
    def labels(self) -> np.ndarray:
        """(N,) int64, the latest labels (-1 unlabelled; all -1 before any vote)."""
        return self._labels

    @property
    def voted(self) -> int:
        return len(self._acc.frames) if self._acc is not None else 0

    def result(self) -> StageOneOutput:
        if self._out is None:
            raise RuntimeError("Stage I has not finished: drain stream() (or call run()) first")
        return self._out

    def vote_so_far(self) -> VoteResult:
        """The labels, histogram and statistics of the views voted so far (a stopped run's)."""
        if self._out is not None:
            return self._out.vote.value
        if self._acc is None or not self._acc.frames:
            raise PromptError("no view has voted yet")
        return self._acc.result()

    # --- inside -------------------------------------------------------------------------------

    def _reset(self) -> None:
        self._events: Iterator[Event] | None = None
        self._acc: VoteAccumulator | None = None
        self._out: StageOneOutput | None = None
        self.masks: list[np.ndarray | None] = [None] * len(self.cameras)
        self._labels = np.full(len(self.gaussians), -1, np.int64)

    def _all_events(self) -> Iterator[Event]:
        yield from self._frame_events()
        yield from self._mask_and_vote_events()

    def _frame_events(self) -> Iterator[FrameRendered]:
        if self.frames is not None:
            return
        c = self.config
        inputs = FramesInputs(
            self.gaussians,
            list(self.cameras),
            self.plan.images,
            implementation_digest(self.plan.images),
            tuple(c.settings.background),
            self.device,
        )
        key, start = FRAMES.key(inputs), time.perf_counter()
        given = c.rendered.value if c.rendered is not None and c.rendered.key == key else None
        cached = None if c.keep_depth else given or self.cache.load(FRAMES, key)
        if cached is not None:
            for i, image in enumerate(cached.images):
                yield FrameRendered(i, image, cached=True)
            frames = cached
        else:
            images, bg = [], torch.tensor(c.settings.background)
            with torch.no_grad():
                for i, cam in enumerate(self.cameras):
                    out = render(self.gaussians, cam, background=bg, backend=self.plan.images)
                    images.append(np.ascontiguousarray(to_uint8(out.rgb)))
                    if c.keep_depth:
                        alpha = out.alpha.detach().float().cpu().numpy()
                        depth = out.depth.detach().float().cpu().numpy() / np.maximum(alpha, 1e-6)
                        self.alphas.append(alpha)
                        self.depths.append(np.where(alpha > 0.5, depth, np.inf))
                    yield FrameRendered(i, images[-1])
            frames = Frames(images, (time.perf_counter() - start) / len(images))
            self.cache.save(FRAMES, key, frames)
        self.frames, self._frames_out = frames.images, Output(key, frames)
        status = "cached" if cached is not None else "computed"
        self.runs["frames"] = StageRun(status, time.perf_counter() - start)

    def _mask_source(self, masks_in: MasksInputs, cached: SegmentationResult | None):
        """(frame, mask, seconds) in the order the masks are made (or were, when cached)."""
        c = self.config
        if cached is not None:
            order = cached.info.get("order") or [
                self._prompt.frame,
                *(i for i in range(len(cached.masks)) if i != self._prompt.frame),
            ]
            return ((i, cached.masks[i], cached.seconds[i]) for i in order), None
        segmenter = c.segmenter.segmenter
        if masks_in.feedback is None:
            advice = None
            if masks_in.advice is not None:
                advice = FusedRender(masks_in.advice, self._acc, masks_in.advice.config.min_frames)
            stream = segmenter.stream(
                self.frames, self._prompt, ground_truth=c.trajectory_gt, advice=advice
            )
            return stream, advice
        policy = FeedbackPolicy(masks_in.feedback)
        masks = policy.masks(segmenter, self.frames, self._prompt, self._acc, c.trajectory_gt)
        return masks, policy

    def _mask_and_vote_events(self) -> Iterator[MaskReady | ViewVoted | LabelsUpdated]:
        c = self.config
        masks_in, masks_key, vote_key = stage_keys(
            self.config,
            self.gaussians,
            self.cameras,
            self.plan,
            self._frames_out,
            self._prompt,
            self.device,
        )
        start = time.perf_counter()
        cached_masks = self.cache.load(MASKS, masks_key)
        cached_vote = self.cache.load(VOTE, vote_key)
        self._acc = VoteAccumulator(
            len(self.gaussians),
            max(c.num_labels, self._prompt.num_labels),
            c.vote,
            self.gaussians.device,
            self.gaussians.means,
            extents(self.gaussians) if c.vote.body else None,
        )
        voting, total = set(self.voting), len(self.voting)
        seconds = [0.0] * len(self.cameras)
        order: list[int] = []
        since = 0
        source, policy = self._mask_source(masks_in, cached_masks)
        for i, mask, took in source:
            self.masks[i], seconds[i] = mask, took
            order.append(i)
            self._acc.grow(int(mask.max(initial=0)) + 1)
            yield MaskReady(i, mask, took, cached=cached_masks is not None)
            if cached_vote is not None or i not in voting:
                continue
            where = f"mask of view {i} ('{self.cameras[i].name}')"
            self._acc.add_view(self.gaussians, self.cameras[i], mask, self.plan.vote, where, i)
            yield ViewVoted(i, len(self._acc.frames), total)
            since += 1
            if c.publish_every and (len(self._acc.frames) == 1 or since >= c.publish_every):
                since = 0
                self._labels = self._acc.labels().cpu().numpy().copy()  # the vote keeps its own
                yield LabelsUpdated(self._labels, len(self._acc.frames), total)
        name = c.segmenter.segmenter.name
        info = {"order": order, **c.segmenter.segmenter.describe()}
        if isinstance(policy, FeedbackPolicy):
            info["feedback"] = policy.stats
        elif isinstance(policy, FusedRender):
            info["advice"] = {"renders": policy.renders, "render_s": policy.render_s}
        if cached_masks is not None:
            seg = cached_masks
        else:
            seg = SegmentationResult([label_map(m) for m in self.masks], seconds, name, info)
            self.cache.save(MASKS, masks_key, seg)
        vote = cached_vote if cached_vote is not None else self._acc.result()
        if cached_vote is None:
            self.cache.save(VOTE, vote_key, vote)
        elapsed = time.perf_counter() - start
        vote_s = vote.stats.get("aggregation_s", 0.0) if cached_vote is None else 0.0
        self.runs["masks"] = StageRun("cached" if cached_masks else "computed", elapsed - vote_s)
        self.runs["vote"] = StageRun("cached" if cached_vote else "computed", vote_s)
        num_labels = max(c.num_labels, self._acc.k, vote.histogram.shape[1])
        voted = {self.cameras[i].name for i in vote.frames}
        self._out = StageOneOutput(
            self._frames_out,
            Output(masks_key, seg),
            Output(vote_key, vote),
            num_labels,
            voted,
            dict(self.runs),
            self.plan,
        )
        self._labels = vote.labels.cpu().numpy()
        yield LabelsUpdated(self._labels, len(vote.frames), total, final=True)


def compose_stage_one(
    gaussians: Gaussians,
    trajectory: list[Camera],
    prompt: Prompt,
    segmenter: SegmenterRun,
    vote: VoteConfig,
    settings: PipelineSettings,
    *,
    num_labels: int,
    trajectory_gt: list[np.ndarray] | None = None,
    cache: StageCache | None = None,
    rendered: Output[Frames] | None = None,
) -> StageOneOutput:
    """Stage I drained in one call (`StageOne(...).run()`), for callers that want its outputs
    and no events (`rendered`: another run's frames, `StageOneConfig`)."""
    config = StageOneConfig(
        gaussians, list(trajectory), segmenter, vote, settings, num_labels, trajectory_gt, cache
    )
    return StageOne(replace(config, rendered=rendered), prompt).run()
