"""`sagonline segment SCENE`: a scene of one's own segmented from clicks, masks or text, written
as labels, object PLYs, renders and a recording (`sagonline.labels.export.write_segmentation`)."""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict
from pathlib import Path

from sagonline.apps.cli import CLICK_HELP
from sagonline.apps.cli.options import (
    add_min_weight_argument,
    add_segmenter_arguments,
    add_vote_arguments,
    build_segmenter,
    label_min_weight,
    segmenter_options,
    vote_config,
)
from sagonline.apps.cli.render import (
    add_every_argument,
    add_view_arguments,
    find_cameras,
    recorded_path,
    views_of,
)
from sagonline.core.machine import BACKENDS
from sagonline.segment.base import DEFAULT_SEGMENTER
from sagonline.segment.clicks import parse_prompt, to_prompt


class PromptItems(argparse.Action):
    """Keeps --click, --object, --mask and --text in the order given."""

    def __call__(self, parser, namespace, value, option_string=None):
        items = list(getattr(namespace, "prompt_items", None) or [])
        items.append((option_string.lstrip("-"), value))
        namespace.prompt_items = items


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    seg = command_parser(sub, "segment")
    seg.add_argument("scene", help="point_cloud.ply, .splat, or a folder holding one")
    add_view_arguments(seg)
    prompts = seg.add_argument_group(f"prompts (all on one view; {CLICK_HELP})")
    prompts.add_argument(
        "--click",
        action=PromptItems,
        metavar="VIEW:X,Y[:neg[=NAME]]",
        help="a positive click on the current object, or a negative one (:neg)",
    )
    prompts.add_argument(
        "--object", action=PromptItems, metavar="NAME", help="start an object named NAME"
    )
    prompts.add_argument(
        "--mask",
        action=PromptItems,
        metavar="VIEW:PATH",
        help="a mask at the view's render size: binary (the current object) or a label map "
        "(one object per id)",
    )
    prompts.add_argument("--text", action=PromptItems, metavar="TEXT", help="a text prompt (SAM 3)")
    prompts.add_argument(
        "--prompts",
        metavar="LABELS_JSON",
        help="the prompts (and views, segmenter, vote) a segment folder or a viewer export "
        "recorded in its labels.json; what the command line gives wins",
    )
    seg.add_argument(
        "--preview",
        metavar="VIEW",
        help="write VIEW at the render size with a pixel grid (to pick clicks on), and exit; "
        "all: every view small in one image, with its index",
    )
    add_segmenter_arguments(seg, default=None)
    add_vote_arguments(seg)
    add_min_weight_argument(seg)
    add_every_argument(
        seg, "render and segment every N-th view only (0, N, 2N, ... and the prompt's view)"
    )
    seg.add_argument("--inbetween", type=int, default=0, help="views slerped between cameras")
    seg.add_argument("--backend", default="auto", choices=BACKENDS)
    seg.add_argument("--out", help="output folder (default: segment-<scene>-<time>)")
    seg.add_argument(
        "--overwrite", action="store_true", help="replace an earlier output of this command"
    )
    seg.add_argument("--no-record", action="store_true", help="skip the rerun recording")
    seg.set_defaults(func=cmd_segment, prompt_items=[])


# --- segmenter and vote -----------------------------------------------------------------------


# --- the command ------------------------------------------------------------------------------


def cmd_segment(args) -> int:
    from sagonline.apps.cli.recorded import apply_recorded_prompts
    from sagonline.core.machine import check_device
    from sagonline.pipeline.segment import (
        check_cameras_see_scene,
        check_objects_were_found,
        segment_scene,
        write_segment_folder,
    )
    from sagonline.render.api import resolve_backend
    from sagonline.scene.io import fitted_background, read_scene, scene_file
    from sagonline.scene.io.cameras import camera_input_files
    from sagonline.scene.views import check_trajectory, every_line, trajectory

    started = time.perf_counter()
    replay = apply_recorded_prompts(args) if args.prompts else None
    args.segmenter = args.segmenter or DEFAULT_SEGMENTER
    scene = scene_file(args.scene)
    find_cameras(args, scene)
    args.device = check_device(args.device)
    resolve_backend(args.backend, args.device)
    check_trajectory_options(args)
    masks = [Path(v.partition(":")[2]) for k, v, *_ in args.prompt_items if k == "mask"]
    inputs = [scene, *(camera_input_files(args.cameras) if args.cameras else []), *masks]
    out = output_of(args, scene, inputs)
    vote, min_weight = vote_config(args, replay), label_min_weight(args, replay)
    g = read_scene(scene, drop_nonfinite=args.drop_nonfinite)
    background = fitted_background(scene) or (0.0, 0.0, 0.0)  # the colour it was fitted on
    views = views_of(args, g, say=True)
    given = views.cameras
    if args.preview is not None:
        from sagonline.apps.cli.preview import write_preview

        return write_preview(g, given, args.preview, out, args, background)
    parsed = parse_prompt(args.prompt_items, given)
    traj = trajectory(given, every=args.every, keep=parsed.view, inbetween=args.inbetween)
    check_trajectory(traj)
    frame = [c.name for c in traj].index(given[parsed.view].name)
    prompt = to_prompt(parsed, frame)
    from sagonline.labels.export import object_file_names

    object_file_names(prompt.names)  # names that cannot each have a file: refused now
    segmenter = build_segmenter(args, prompt, replay)
    check_cameras_see_scene(g, traj)  # another scene's cameras: said before any click is
    check_clicks_hit_the_scene(g, given[parsed.view], parsed, args)
    views_line = every_line(given, args.every, parsed.view, len(traj))
    print(f"segmenting {views_line} with {args.segmenter} ...", file=sys.stderr)
    seg = segment_scene(
        g,
        traj,
        prompt,
        segmenter=segmenter,
        vote=vote,
        backend=args.backend,
        device=args.device,
        progress=True,
        background=background,
    )
    check_objects_were_found(seg)
    info = segment_record(args, scene, views, parsed, given, out, masks, segmenter, vote, seg)
    write_segment_folder(
        out,
        g,
        seg,
        scene,
        info,
        backend=args.backend,
        device=args.device,
        min_weight=min_weight,
        record=not args.no_record,
        overwrite=args.overwrite,
        inputs=inputs,
        progress=progress,
    )
    print_segmentation(seg, out, time.perf_counter() - started)
    return 0


def check_trajectory_options(args) -> None:
    """--inbetween in [0, 32]; --every 1 or more (1 where neither it nor --prompts gave one)."""
    from sagonline.scene.views import check_every

    if args.inbetween < 0 or args.inbetween > 32:
        raise ValueError(f"--inbetween {args.inbetween}: must be in [0, 32]")
    args.every = check_every(args.every)


def output_of(args, scene: Path, inputs: list[Path]) -> Path:
    """Where `segment` writes: the preview's image, or the segmentation's folder (named after
    the scene and the time), never one of its inputs nor, without --overwrite, a finished
    folder."""
    from sagonline.core.outputs import check_not_input, check_replaceable

    stem = scene.parent.name if scene.name == "point_cloud.ply" else scene.stem
    if args.preview is not None:
        out = Path(args.out or f"preview-{stem}-{args.preview}.png")
    else:
        out = Path(args.out or f"segment-{stem}-{time.strftime('%Y%m%d-%H%M%S')}")
    check_not_input(out, inputs)
    if args.preview is None:
        check_replaceable(out, args.overwrite)
    return out


def segment_record(args, scene, views, parsed, given, out, masks, segmenter, vote, seg) -> dict:
    """What labels.json records of a `segment` run: the scene, views, prompt, inputs'
    digests, the segmenter with its options and weights, the vote and the timings."""
    return {
        "scene": recorded_path(scene),
        "cameras": recorded_path(args.cameras),
        "views": views.source,
        "orbit": args.orbit,
        "inside": args.inside,
        "every": args.every,
        "inbetween": args.inbetween,
        "prompt": parsed.record(given, folder=out),
        "inputs": input_digests(scene, args.cameras, masks),
        "segmenter": {
            "kind": args.segmenter,
            "options": segmenter_options(args),
            "weights": segmenter.weights_record(),
        },
        "vote": asdict(vote),
        "timings": seg.timings,
    }


def check_clicks_hit_the_scene(g, cam, parsed, args) -> None:
    """Refuse a positive click where nothing of the scene is rendered (`check_click_on_scene`)."""
    from sagonline.pipeline.segment import check_click_on_scene
    from sagonline.render.api import render

    alpha = render(g.to(args.device), cam.to(args.device), backend=args.backend).alpha
    alpha = alpha.detach().cpu().numpy()
    for obj in parsed.objects:
        for x, y in obj.points:
            check_click_on_scene(alpha, cam, parsed.view, x, y, obj.name, hint="`--preview`")


def input_digests(scene: Path, cameras: str | None, masks: list[Path]) -> dict:
    from sagonline.core.provenance import digest_file
    from sagonline.scene.io.cameras import camera_digests

    out = {"scene": digest_file(scene), **(camera_digests(cameras) if cameras else {})}
    return out | {f"mask:{p.name}": digest_file(p) for p in masks}


def progress(items: list, what: str):
    """A bar on a terminal; elsewhere (a log file, CI) a line every 15 s and one when done."""
    from sagonline.core.progress import progress as said

    yield from said(items, what, len(items))


def print_segmentation(seg, out: Path, wall_s: float) -> None:
    t = seg.timings
    counts = ", ".join(f"{name} {int((seg.labels == k).sum())}" for k, name in enumerate(seg.names))
    print(
        f"time to first mask {t['time_to_first_mask_s']:.2f} s, aggregation "
        f"{t['vote_ms_per_mask']:.1f} ms per mask ({len(seg.vote.frames)} masks), coverage "
        f"{100 * seg.coverage:.1f}% of {len(seg.labels)} Gaussians ({counts}, unlabelled "
        f"{int((seg.labels < 0).sum())}), {wall_s:.1f} s in all -> {out}"
    )
