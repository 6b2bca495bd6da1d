"""`sagonline segment` (a scene of one's own, from clicks, a mask or text) and `sagonline
export` (a finished eval run's labels): both write `sagonline.export.write_segmentation`'s
folder."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np


class PromptItems(argparse.Action):
    """Keeps --click, --object, --mask and --text in the order given (an --object starts a new
    object for the clicks after it)."""

    def __call__(self, parser, namespace, value, option_string=None):
        items = list(getattr(namespace, "prompt_items", None) or [])
        items.append((option_string.lstrip("-"), value))
        namespace.prompt_items = items


def add_parsers(sub) -> None:
    seg = sub.add_parser(
        "segment",
        help="segment a scene from clicks, a mask or text; write labels, object PLYs, renders",
    )
    seg.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    seg.add_argument(
        "--cameras", required=True, help="COLMAP sparse/0, transforms.json, poses_bounds.npy, ..."
    )
    prompts = seg.add_argument_group("prompts (on one view; VIEW: an index or a camera name)")
    prompts.add_argument("--click", action=PromptItems, metavar="VIEW:X,Y[:neg[=NAME]]")
    prompts.add_argument("--object", action=PromptItems, metavar="NAME")
    prompts.add_argument("--mask", action=PromptItems, metavar="VIEW:PATH.png")
    prompts.add_argument("--text", action=PromptItems, metavar="TEXT")
    seg.add_argument("--segmenter", default="classical", choices=["classical", "sam2", "sam3"])
    seg.add_argument("--checkpoint", help="the model's local checkpoint (sam2, sam3)")
    seg.add_argument("--method", default="rgc", choices=["rgc", "flashsplat", "weighted_mean"])
    seg.add_argument("--eps", type=float, default=0.01)
    seg.add_argument("--delta", type=float, default=2.0)
    seg.add_argument("--min-votes", type=int, default=1)
    seg.add_argument("--margin", type=float, default=0.2)
    seg.add_argument("--width", type=int, help="render width (cameras rescaled)")
    seg.add_argument("--height", type=int)
    seg.add_argument("--inbetween", type=int, default=0, help="views slerped between cameras")
    seg.add_argument(
        "--orbit", type=int, default=0, metavar="N",
        help="N views turned about the scene around the first camera (a scene with one camera)",
    )  # fmt: skip
    seg.add_argument("--device", default="cpu")
    seg.add_argument("--backend", default="auto", choices=["torch", "native", "gsplat", "auto"])
    seg.add_argument("--out", help="output folder (default: segment-<scene>-<time>)")
    seg.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    seg.add_argument("--no-record", action="store_true", help="skip the rerun recording")
    seg.set_defaults(func=cmd_segment, prompt_items=[])
    exp = sub.add_parser("export", help="a finished eval run's labels as files (per scene)")
    exp.add_argument("run_dir")
    exp.add_argument("--out", help="output folder (default: <run_dir>/export)")
    exp.add_argument("--overwrite", action="store_true")
    exp.set_defaults(func=cmd_export)


# --- segment ----------------------------------------------------------------------------------


def trajectory(args, gaussians) -> tuple[list, list]:
    """The given cameras in the harness's order (by name), rescaled, with in-between views, or
    an orbit of `--orbit` views from the first; returns (trajectory, the views VIEW counts)."""
    from sagonline.io.cameras import load_cameras
    from sagonline.trajectory import insert_between, pseudo_temporal_order, ring_around

    cams = pseudo_temporal_order(load_cameras(args.cameras))
    if args.orbit < 0 or args.orbit == 1:
        raise SystemExit("error: --orbit takes at least 2 views")
    if args.orbit:
        center = gaussians.means.detach().float().median(dim=0).values.cpu().numpy()
        cams = ring_around(cams[0], center, args.orbit)
    if (args.width is None) != (args.height is None):
        raise SystemExit("error: give both --width and --height, or neither")
    if args.width is not None:
        try:
            cams = [c.scaled(args.width, args.height) for c in cams]
        except ValueError as exc:
            raise SystemExit(f"error: --width {args.width} --height {args.height}: {exc}") from None
    if args.inbetween < 0:
        raise SystemExit("error: --inbetween must be >= 0")
    return insert_between(cams, args.inbetween), cams


def view_index(text: str, given: list, traj: list) -> int:
    """A VIEW (an index into the given cameras, or a camera's name) -> its trajectory index."""
    from sagonline.segment import PromptError

    names = [c.name for c in given]
    if text.lstrip("-").isdigit():
        i = int(text)
        if not 0 <= i < len(given):
            raise PromptError(
                f"view {i} is out of range: there are {len(given)} cameras (0..{len(given) - 1})"
            )
        name = names[i]
    elif text in names:
        name = text
    else:
        raise PromptError(f"no camera named {text!r} (cameras: {names[0]} ... {names[-1]})")
    return [c.name for c in traj].index(name)


def parse_prompt(items: list[tuple[str, str]], given: list, traj: list):
    """--click / --object / --mask / --text, in order -> (Prompt, label names)."""
    from PIL import Image

    from sagonline.prompts import Prompt
    from sagonline.segment import PromptError, clicks_prompt, mask_prompt

    clicks: dict[str, list] = {}
    negatives: dict[str, list] = {}
    texts, current, views = [], None, set()
    for kind, value in items:
        if kind == "object":
            current = value
            clicks.setdefault(current, [])
        elif kind == "text":
            texts.append(value)
        elif kind == "mask":
            view, _, path = value.partition(":")
            frame = view_index(view, given, traj)
            try:
                mask = np.asarray(Image.open(path))
            except OSError as exc:
                raise PromptError(
                    f"--mask {value}: {path} is not a readable image ({exc})"
                ) from None
            prompt, names = mask_prompt(traj, frame, mask)
            if current is not None and len(prompt.objects) == 1:  # --object NAME --mask ...
                names = ["background", current]
            return prompt, names
        elif kind == "click":
            parts = value.split(":")
            if len(parts) < 2 or len(parts) > 3:
                raise PromptError(f"--click {value}: expected VIEW:X,Y or VIEW:X,Y:neg[=NAME]")
            views.add(view_index(parts[0], given, traj))
            try:
                x, y = (float(v) for v in parts[1].split(","))
            except ValueError:
                raise PromptError(f"--click {value}: X,Y must be two numbers") from None
            if len(parts) == 3:
                flag, _, name = parts[2].partition("=")
                if flag != "neg":
                    raise PromptError(f"--click {value}: the third part must be neg or neg=NAME")
                target = name or current
                if target is None or target not in clicks:
                    raise PromptError(
                        f"--click {value}: no object {target!r} to add a negative click to"
                    )
                negatives.setdefault(target, []).append((x, y))
            else:
                current = current or "object"
                clicks.setdefault(current, []).append((x, y))
    if len(views) > 1:
        raise PromptError("clicks on several views: the segmenter takes prompts on one view")
    if texts and not clicks:
        return Prompt(frame=0, texts=texts), ["background", *texts]
    if not clicks:
        raise PromptError("no prompt: give --click, --mask or --text")
    return clicks_prompt(traj, views.pop(), clicks, negatives)


def build_segmenter(args):
    if args.segmenter == "classical":
        from sagonline.segmenters.classical import FlowWatershedSegmenter

        return FlowWatershedSegmenter()
    if not args.checkpoint:
        raise SystemExit(
            f"error: --segmenter {args.segmenter} needs --checkpoint PATH (a local file)"
        )
    if args.segmenter == "sam2":
        from sagonline.segmenters.sam2_video import SAM2VideoSegmenter

        seg = SAM2VideoSegmenter(checkpoint=args.checkpoint, device=args.device)
    else:
        from sagonline.segmenters.sam3_text import SAM3TextSegmenter

        seg = SAM3TextSegmenter(checkpoint=args.checkpoint, device=args.device)
    seg.check()
    return seg


def cmd_segment(args) -> int:
    from sagonline.__main__ import scene_file
    from sagonline.consensus import VoteConfig
    from sagonline.export import OutputExists
    from sagonline.io import read_scene
    from sagonline.segment import PromptError, segment_scene

    started = time.perf_counter()
    scene = scene_file(args.scene)
    stem = scene.parent.name if scene.name == "point_cloud.ply" else scene.stem
    out = Path(args.out or f"segment-{stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and not args.overwrite:
        raise SystemExit(f"error: {out} exists; pass --overwrite to replace it")
    g = read_scene(scene)
    try:
        vote = VoteConfig(args.method, args.eps, args.delta, args.min_votes, args.margin)
        traj, given = trajectory(args, g)
        prompt, names = parse_prompt(args.prompt_items, given, traj)
        segmenter = build_segmenter(args)
    except (PromptError, ValueError, RuntimeError, OSError) as exc:
        raise SystemExit(f"error: {exc}") from None
    try:
        seg = segment_scene(
            g, traj, (prompt, names), segmenter=segmenter, vote=vote, backend=args.backend,
            device=args.device, progress=sys.stderr.isatty(),
        )  # fmt: skip
    except PromptError as exc:
        raise SystemExit(f"error: {exc}") from None
    info = {
        "scene": str(scene),
        "cameras": str(args.cameras),
        "inputs": input_digests(scene, args.cameras),
        "segmenter": args.segmenter,
        "vote": asdict(vote),
        "timings": seg.timings,
    }
    try:
        write_outputs(out, g, seg, scene, info, args)
    except OutputExists as exc:
        raise SystemExit(f"error: {exc}") from None
    print_segmentation(seg, out, time.perf_counter() - started)
    return 0


def input_digests(scene: Path, cameras: str) -> dict:
    from sagonline.io.cameras import camera_input_files
    from sagonline.provenance import digest_file

    return {"scene": digest_file(scene)} | {
        f"cameras:{p.name}": digest_file(p) for p in camera_input_files(cameras)
    }


def write_outputs(out: Path, g, seg, scene: Path, info: dict, args) -> None:
    """Label renders of every trajectory view, the recording, the files."""
    import torch

    from sagonline.export import write_segmentation
    from sagonline.recording import Recorder
    from sagonline.render.api import render_labels

    labels = torch.from_numpy(seg.labels)
    known = labels >= 0
    views = []
    for cam, frame in zip(seg.cameras, seg.frames, strict=True):
        lab = render_labels(
            g.to(args.device), cam, labels.clamp_min(0), len(seg.names),
            labelled=known & (labels > 0), backend=args.backend,
        )  # fmt: skip
        views.append((cam.name, frame, lab.cpu().numpy()))

    def record(path: Path) -> None:
        rec = Recorder(path, scenes=["segment"])
        rec.annotate("segment", seg.names)
        for i, (cam, frame, mask) in enumerate(
            zip(seg.cameras, seg.frames, seg.masks, strict=True)
        ):
            rec.trajectory_frame("segment", i, frame, mask, camera=cam)
        rec.gaussians("segment", g, seg.labels.clip(0), seg.labels >= 0, seg.vote.histogram.numpy())
        rec.close()

    write_segmentation(
        out, g, seg.labels, seg.names, source=scene, info=info, views=views,
        record=None if args.no_record else record, overwrite=args.overwrite,
    )  # fmt: skip


def print_segmentation(seg, out: Path, wall_s: float) -> None:
    t = seg.timings
    counts = ", ".join(f"{name} {int((seg.labels == k).sum())}" for k, name in enumerate(seg.names))
    print(
        f"time to first mask {t['time_to_first_mask_s']:.2f} s, aggregation "
        f"{t['vote_ms_per_mask']:.1f} ms per mask ({len(seg.vote.frames)} masks), coverage "
        f"{100 * seg.coverage:.1f}% of {len(seg.labels)} Gaussians ({counts}, unlabelled "
        f"{int((seg.labels < 0).sum())}), {wall_s:.1f} s in all -> {out}"
    )


# --- export -----------------------------------------------------------------------------------


def cmd_export(args) -> int:
    import torch
    from hydra.utils import instantiate

    from sagonline.export import OutputExists, write_segmentation
    from sagonline.io import store

    run = Path(args.run_dir)
    try:
        metrics = json.loads((run / "metrics.json").read_text())
        config = metrics["config"]
    except (OSError, ValueError, KeyError) as exc:
        raise SystemExit(f"error: {run}: not a finished eval run ({exc})") from None
    recorded = metrics.get("cache_root") or config.get("cache_dir")
    cache_root = Path(recorded) if recorded else run / "cache"
    out_root = Path(args.out) if args.out else run / "export"
    adapter = instantiate(config["dataset"]["adapter"])
    done = 0
    for scene in metrics.get("scenes", []):
        key = (scene.get("stage_keys") or {}).get("vote")
        if scene.get("status") != "ok" or key is None:
            print(f"warning: {scene['scene']}: no vote recorded; skipped", file=sys.stderr)
            continue
        path = cache_root / scene["scene"] / f"vote-{key}{store.SUFFIX}"
        try:
            vote = store.load(path)
        except store.StoreError as exc:
            raise SystemExit(f"error: {exc} (was the run made with cache=false?)") from None
        task = adapter.load_scene(scene["scene"])
        labels = torch.where(vote.labelled, vote.labels, torch.full_like(vote.labels, -1))
        k = int(vote.histogram.shape[1])
        names = list(task.label_names or ["background"])
        names += [f"id_{i}" for i in range(len(names), k)]
        source = task.meta.get("scene_file")
        info = {"run": str(run), "scene": scene["scene"], "vote_key": key,
                "vote": metrics.get("consensus"), "protocol": metrics.get("protocol")}  # fmt: skip
        try:
            write_segmentation(
                out_root / scene["scene"], task.gaussians, labels.numpy(), names[:k],
                source=Path(source) if source else None, info=info, overwrite=args.overwrite,
            )  # fmt: skip
        except OutputExists as exc:
            raise SystemExit(f"error: {exc}") from None
        done += 1
        print(
            f"{scene['scene']}: {int((labels >= 0).sum())} of {len(labels)} Gaussians "
            f"labelled -> {out_root / scene['scene']}"
        )
    return 0 if done else 1
