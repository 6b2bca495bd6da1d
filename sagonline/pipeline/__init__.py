"""Stage I's engine and what composes around it: cached stages, scoring, Stage II.

- `graph`: stages as typed keys over their inputs, and the cache of their outputs;
- `stages`: the frames, masks, vote and refine stages and their inputs dataclasses;
- `settings`: `PipelineSettings`, how a scene is run (backends, device, feedback, ...);
- `stage_one`: `StageOne`, the one engine every front end streams from (render -> masks ->
  vote -> labels, as events), and `compose_stage_one`, the same drained in one call;
- `scene`: `run_scene`, Stage I on a dataset's scene, scored and recorded;
- `segment`: `segment_scene`, Stage I on a scene of one's own, and the segment folder;
- `diagnose`: every scored view's wrong pixels sorted by cause (fit, vote, segmenter);
- `scoring`: per-view rows, view groups, the dataset-level summary;
- `recorded`: a finished run read back from its metrics.json (`sagonline export`);
- `stage_two`: the refinement student trained in the background.
"""

from sagonline.pipeline.graph import Output, Stage, StageCache
from sagonline.pipeline.scene import input_digests, run_scene
from sagonline.pipeline.scoring import SceneReport, record_scores, summarize
from sagonline.pipeline.settings import PipelineSettings
from sagonline.pipeline.stage_one import (
    FrameRendered,
    LabelsUpdated,
    MaskReady,
    StageOne,
    StageOneConfig,
    StageOneOutput,
    ViewVoted,
    compose_stage_one,
)
from sagonline.pipeline.stage_two import run_stage_two, student_checkpoint
from sagonline.pipeline.stages import STAGE_VERSIONS, STAGES, SegmenterRun

__all__ = [
    "STAGES",
    "STAGE_VERSIONS",
    "FrameRendered",
    "LabelsUpdated",
    "MaskReady",
    "Output",
    "PipelineSettings",
    "SceneReport",
    "SegmenterRun",
    "Stage",
    "StageCache",
    "StageOne",
    "StageOneConfig",
    "StageOneOutput",
    "ViewVoted",
    "compose_stage_one",
    "input_digests",
    "record_scores",
    "run_scene",
    "run_stage_two",
    "student_checkpoint",
    "summarize",
]
