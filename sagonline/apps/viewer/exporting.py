"""A viewer session taken with you: what it holds as `segment_scene` gives it, and the folder
`sagonline segment` writes from it (`sagonline segment --prompts OUT/labels.json` reproduces it
without the browser)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from sagonline.core.errors import PromptError
from sagonline.core.provenance import digest_file
from sagonline.pipeline.segment import Segmentation, check_objects_were_found, write_segment_folder


def segmentation_of(session) -> Segmentation:
    """What the session (a `viewer.session.SegmentSession`) holds as `segment_scene` gives it
    (views without a mask yet, after a Stop, carry an empty one)."""
    if session.progress.voted == 0:
        raise PromptError("nothing to export yet: click on the object and let a view vote")
    masks = [
        m if m is not None else np.zeros(f.shape[:2], np.int64)
        for m, f in zip(session.engine.masks, session.frames, strict=True)
    ]
    return Segmentation(
        session.labels.copy(),
        session.names,
        session.engine.vote_so_far(),
        list(session.cameras),
        session.frames,
        masks,
        {"render_s": session.render_seconds},
        session.view or 0,
    )


def export_session(
    session,
    out: Path,
    *,
    scene: Path | None = None,
    info: dict | None = None,
    overwrite: bool = False,
    record: bool = True,
) -> Path:
    """The folder `sagonline segment` writes (objects/<name>.ply, scene_without_<name>.ply,
    labels.npy, labels.json with this session's prompt, the recording): `sagonline segment
    --prompts OUT/labels.json` reproduces it without the browser."""
    seg = segmentation_of(session)
    check_objects_were_found(seg)
    prompt = session.parsed().record(session.cameras)
    prompt["view"] *= int((info or {}).get("every") or 1)  # its number in `sagonline cameras`
    full = {
        "scene": str(scene) if scene else None,
        "inputs": {"scene": digest_file(scene)} if scene else {},
        "prompt": prompt,
        "segmenter": {
            "kind": session.segmenter_kind,
            "options": list(session.segmenter_options),
            "weights": session.segmenter.weights_record(),
        },
        "vote": asdict(session.vote),
        "viewer": {
            "views_voted": session.progress.voted,
            "views": len(session.cameras),
            "state": session.progress.state,
        },
        **(info or {}),
    }
    inputs = [scene] if scene else []
    return write_segment_folder(
        Path(out),
        session.gaussians,
        seg,
        scene,
        full,
        backend=session.backend,
        device=session.device,
        record=record,
        overwrite=overwrite,
        inputs=inputs,
        min_weight=session.min_weight,
    )
