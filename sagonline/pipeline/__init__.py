"""One scene through the method: cached stages (frames -> masks -> vote), scoring, Stage II.

- `graph`: stages as typed functions, keyed by the digest of every field of their inputs;
- `stages`: the frames, masks, vote and refine stages and their inputs dataclasses;
- `scene`: `run_scene`, Stage I composed from them, scored and recorded;
- `scoring`: per-view rows, view groups, the dataset-level summary;
- `stage_two`: the refinement student trained in the background.
"""

from sagonline.pipeline.graph import Output, Stage, StageCache, run_stage
from sagonline.pipeline.scene import (
    PipelineSettings,
    StageOneOutput,
    input_digests,
    run_scene,
)
from sagonline.pipeline.scoring import SceneReport, record_scores, summarize
from sagonline.pipeline.stage_two import run_stage_two, student_checkpoint
from sagonline.pipeline.stages import STAGE_VERSIONS, STAGES, SegmenterRun

__all__ = [
    "STAGES",
    "STAGE_VERSIONS",
    "Output",
    "PipelineSettings",
    "SceneReport",
    "SegmenterRun",
    "Stage",
    "StageCache",
    "StageOneOutput",
    "input_digests",
    "record_scores",
    "run_scene",
    "run_stage",
    "run_stage_two",
    "student_checkpoint",
    "summarize",
]
