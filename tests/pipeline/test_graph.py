"""Cache keys derived from the stages' inputs dataclasses: a change to any field recomputes
exactly its stage and the ones downstream. Generated from the dataclasses: a field added to an
inputs dataclass (or to a settings dataclass inside one) without a way to change it here fails
`test_every_field_has_a_change`, so the test cannot drift from the code."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sagonline.pipeline.graph import Output, digest_value
from sagonline.pipeline.stages import (
    STAGES,
    FeedbackInputs,
    FramesInputs,
    MasksInputs,
    SegmenterRun,
    VoteInputs,
)
from sagonline.refine import RefineConfig
from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians
from sagonline.segment.oracle import OracleSegmenter
from sagonline.segment.prompts import Prompt
from sagonline.vote.consensus import VoteConfig
from sagonline.vote.feedback import FeedbackConfig

# Valid other values for settings whose field is a string, a list or None (numbers and flags are
# changed by rule: see `changed`).
OTHER = {
    "method": "flashsplat",
    "weighting": "blend",
    "selection": "first",
    "encoder": "resnet34",
    "device": "cuda",
    "backend": "torch",
    "pretrained": "/weights/resnet.pth",
    "num_masks": 3,
    "time_budget_s": 5.0,
    "kernel": "another digest",
    "rule_version": "0.1.0+another",
    "render_side": 256,
    "scored_spans": [30],
}
BY_STAGE = {s.name: s for s in STAGES}
WHOLE = (Gaussians, Prompt, SegmenterRun)  # content, changed as a whole; other dataclasses
# (settings) are changed field by field


def upstream_of(stage) -> set[str]:
    """Stages whose output `stage` reads (its fields named after them)."""
    return {f.name for f in dataclasses.fields(stage.inputs) if f.name in BY_STAGE}


def downstream_of(name: str) -> set[str]:
    out, grew = {name}, True
    while grew:
        grew = False
        for s in STAGES:
            if s.name not in out and upstream_of(s) & out:
                out.add(s.name)
                grew = True
    return out


def base_values(task, feedback: bool) -> dict[str, dict]:
    """Every stage's inputs as field -> value (upstream outputs filled in by `keys`)."""
    g, cams = task.gaussians, task.trajectory
    fb = (
        FeedbackInputs(FeedbackConfig(enabled=True), VoteConfig(), g, cams, 2, 0.2, "native")
        if feedback
        else None
    )
    return {
        "frames": dict(
            gaussians=g,
            cameras=cams,
            backend="native",
            kernel="k",
            background=(0.0, 0.0, 0.0),
            device="cpu",
        ),
        "masks": dict(
            prompt=task.prompt,
            trajectory_gt=task.trajectory_gt,
            segmenter=SegmenterRun(OracleSegmenter(), {}),
            feedback=fb,
            advice=fb,
        ),
        "vote": dict(
            gaussians=g,
            cameras=cams,
            num_labels=task.num_labels,
            config=VoteConfig(),
            rule_version="0.1.0+r",
            backend="native",
            kernel="k",
            device="cpu",
        ),
        "refine": dict(config=RefineConfig(), backend="native", device="cpu"),
    }


def keys(values: dict[str, dict]) -> dict[str, str]:
    """The key of every stage, in graph order, each reading its upstream outputs' keys."""
    out: dict[str, str] = {}
    for stage in STAGES:
        fields = dict(values[stage.name])
        for name in upstream_of(stage):
            fields.setdefault(name, Output(out[name], None))
        out[stage.name] = stage.key(stage.inputs(**fields))
    return out


def changed(name: str, value):
    """Another valid value of the same kind, or None when there is no rule for it."""
    if isinstance(value, bool):
        return not value
    if name in OTHER and value != OTHER[name]:
        return OTHER[name]
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value / 2 if value > 0 else 0.25
    if isinstance(value, tuple) and all(isinstance(v, float) for v in value):
        return tuple(v + 0.5 for v in value)
    if isinstance(value, Gaussians):
        moved = value.opacities.clone()
        moved[0] *= 0.5
        return dataclasses.replace(value, opacities=moved)
    if isinstance(value, list) and value and isinstance(value[0], Camera):
        w2c = value[1].world_to_cam.clone()
        w2c[0, 3] += 1e-3
        return [value[0], dataclasses.replace(value[1], world_to_cam=w2c), *value[2:]]
    if isinstance(value, list) and value and isinstance(value[0], np.ndarray):
        first = value[0].copy()
        first[0, 0] = 1 - first[0, 0]
        return [first, *value[1:]]
    if isinstance(value, Prompt):
        return dataclasses.replace(value, frame=value.frame + 1)
    if isinstance(value, SegmenterRun):
        return SegmenterRun(value.segmenter, {**value.settings, "flicker": 0.1})
    if dataclasses.is_dataclass(value):  # a settings dataclass one level further down
        for sub in dataclasses.fields(value):
            new = changed(sub.name, getattr(value, sub.name))
            if new is not None:
                return replaced(value, sub.name, new)
    return None


def replaced(value, name: str, new):
    """`value` with one field changed; a vote setting its method does not read changes with the
    method that reads it (changing it alone is refused)."""
    try:
        return dataclasses.replace(value, **{name: new})
    except ValueError:
        if not isinstance(value, VoteConfig):
            raise
        from sagonline.core.plugins import VOTE_RULES

        method = next(p.key for p in VOTE_RULES if name in VoteConfig(method=p.key).reads())
        return dataclasses.replace(value, method=method, **{name: new})


def field_changes(values: dict, feedback_on: dict):
    """(stage, description, changed values) for every field of every stage's inputs, and for
    every field of a settings dataclass inside one."""
    for stage in STAGES:
        for f in dataclasses.fields(stage.inputs):
            if f.name in BY_STAGE:
                continue  # an upstream output: changed through that stage's own fields
            value = values[stage.name][f.name]
            cases = []
            if value is None and f.name in ("feedback", "advice"):
                cases.append((f.name, feedback_on["masks"][f.name]))
            elif dataclasses.is_dataclass(value) and not isinstance(value, WHOLE):
                for sub in dataclasses.fields(value):
                    new = changed(sub.name, getattr(value, sub.name))
                    cases.append(
                        (
                            f"{f.name}.{sub.name}",
                            None if new is None else replaced(value, sub.name, new),
                        )
                    )
            else:
                cases.append((f.name, changed(f.name, value)))
            for what, new in cases:
                edited = {k: dict(v) for k, v in values.items()}
                if new is not None:
                    edited[stage.name][f.name] = new
                yield stage, what, None if new is None else edited


@pytest.fixture(scope="module")
def bases(tiny_task):
    return {fb: base_values(tiny_task, fb) for fb in (False, True)}


@pytest.mark.parametrize("feedback", [False, True], ids=["feedback off", "feedback on"])
def test_every_field_has_a_change(bases, feedback):
    missing = [
        f"{stage.name}: {what}"
        for stage, what, edited in field_changes(bases[feedback], bases[True])
        if edited is None
    ]
    assert not missing, f"no rule to change {missing}: add one to `changed` / OTHER"


@pytest.mark.parametrize("feedback", [False, True], ids=["feedback off", "feedback on"])
def test_a_changed_field_recomputes_its_stage_and_those_downstream(bases, feedback):
    base = keys(bases[feedback])
    assert keys(bases[feedback]) == base  # the same inputs, the same keys
    checked = 0
    for stage, what, edited in field_changes(bases[feedback], bases[True]):
        if edited is None:
            continue
        now = keys(edited)
        recomputed = {name for name in base if now[name] != base[name]}
        assert recomputed == downstream_of(stage.name), f"{stage.name}.{what}"
        checked += 1
    assert checked > 40


def test_an_input_of_unknown_kind_stops_the_run():
    with pytest.raises(TypeError, match="no digest rule for object"):
        digest_value(object())


def test_stages_take_only_their_inputs(tiny_task):
    frames_in = FramesInputs(
        tiny_task.gaussians, tiny_task.trajectory, "native", "k", (0, 0, 0), "cpu"
    )
    masks_stage = BY_STAGE["masks"]
    with pytest.raises(TypeError, match="takes MasksInputs"):
        masks_stage.key(frames_in)
    assert {MasksInputs, VoteInputs} <= {s.inputs for s in STAGES}


def test_a_plugin_or_kernel_change_is_a_new_entry(bases):
    """The masks' key names the segmenter plug-in's version (its source digest), the vote's
    the vote backend that ran and its kernel's digest."""
    from sagonline.core.plugins import module_version

    base = keys(bases[False])
    other_kernel = {k: dict(v) for k, v in bases[False].items()}
    other_kernel["vote"]["kernel"] = "changed"
    assert keys(other_kernel)["vote"] != base["vote"]
    seg = bases[False]["masks"]["segmenter"]
    assert seg.segmenter.version == module_version("sagonline.segment.oracle")
    assert "+" in seg.segmenter.version and "unknown" not in seg.segmenter.version
