"""One scene through the method: cached stages (frames -> masks -> vote), scoring, Stage II.

- `graph`: stages as typed functions, keyed by the digest of every field of their inputs;
- `stages`: the frames, masks, vote and refine stages and their inputs dataclasses;
- `stage_one`: `compose_stage_one`, Stage I composed from them once, for every command;
- `scene`: `run_scene`, Stage I on a dataset's scene, scored and recorded;
- `diagnose`: every scored view's wrong pixels sorted by cause (fit, vote, segmenter);
- `scoring`: per-view rows, view groups, the dataset-level summary;
- `recorded`: a finished run read back from its metrics.json (`sagonline export`);
- `stage_two`: the refinement student trained in the background.
"""

from sagonline.pipeline.graph import Output, Stage, StageCache, run_stage
from sagonline.pipeline.scene import input_digests, run_scene
from sagonline.pipeline.scoring import SceneReport, record_scores, summarize
from sagonline.pipeline.stage_one import PipelineSettings, StageOneOutput, compose_stage_one
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
    "compose_stage_one",
    "input_digests",
    "record_scores",
    "run_scene",
    "run_stage",
    "run_stage_two",
    "student_checkpoint",
    "summarize",
]
