"""`sagonline export RUN_DIR`: a finished eval run's labels, per scene, as the files `segment`
writes (`sagonline.labels.export`). The run's Stage I is redone from its metrics.json
(`pipeline.recorded`): nothing in the folder is executed or trusted, and the cached stages
are used only where today's inputs give the same keys."""

from __future__ import annotations

import sys
from dataclasses import asdict
from pathlib import Path


def add_parsers(sub) -> None:
    from sagonline.apps.cli import command_parser

    exp = command_parser(sub, "export")
    exp.add_argument("run_dir")
    exp.add_argument(
        "--out",
        help="output folder (default: export-<its parent's name>-<run folder's name> here; "
        "never inside the finished run)",
    )
    exp.add_argument(
        "--overwrite", action="store_true", help="replace earlier exports (and only those)"
    )
    exp.add_argument("--device", help="redo on this device (default: the run's)")
    exp.set_defaults(func=cmd_export)


def default_out(run: Path) -> Path:
    """export-<its parent>-<run> in the current folder: a finished run's folder is left as the
    run wrote it (its metrics.json digests what is in it)."""
    resolved = run.resolve()
    return Path(f"export-{resolved.parent.name}-{resolved.name}")


def cmd_export(args) -> int:
    """Export from the folder the run was started in (`RunMetrics.run_from`), where its
    relative paths (dataset roots, weights, the stage cache) lead, whatever folder this
    command runs in; `--out` and the run folder as given here."""
    import contextlib
    import os

    from sagonline.pipeline.recorded import read_metrics

    here = Path.cwd()
    run = Path(args.run_dir).absolute()
    out_root = (Path(args.out) if args.out else default_out(run)).absolute()
    started = read_metrics(run).run_from() if run.is_dir() else None
    if started is not None and not started.is_dir():
        print(
            f"note: the run was started in {started}, which is not here: its relative paths "
            "(dataset roots, weights) are read from this folder",
            file=sys.stderr,
        )
        started = None
    elif started is not None and started.resolve() != here.resolve():
        print(
            f"note: the run's relative paths (dataset roots, weights, the stage cache) are read "
            f"from {started}, where it was started",
            file=sys.stderr,
        )
    with contextlib.chdir(started or here):
        return export_run(run, out_root, args, shown=lambda p: os.path.relpath(p, here))


def export_run(run: Path, out_root: Path, args, shown) -> int:
    """Each finished scene of the run (an absolute folder) into out_root/<scene>; `shown`
    gives a path as the command prints it."""
    from sagonline.core.machine import check_device
    from sagonline.core.outputs import check_not_input, check_replaceable
    from sagonline.labels.export import write_segmentation
    from sagonline.pipeline.graph import StageCache
    from sagonline.pipeline.recorded import read_recorded_run
    from sagonline.pipeline.scene import task_settings
    from sagonline.pipeline.stage_one import compose_stage_one

    recorded = read_recorded_run(run, device=args.device)
    check_device(recorded.settings.device)
    for note in recorded.notes:
        print(f"note: {note}", file=sys.stderr)
    metrics_file = run / "metrics.json"
    done = 0
    for row in recorded.scenes:
        scene = str(row.get("scene"))
        if row.get("status") != "ok":
            print(f"warning: {scene}: did not finish in the run; skipped", file=sys.stderr)
            continue
        task = recorded.adapter.load_scene(scene)
        source = task.meta.get("scene_file")
        inputs = [metrics_file, *([Path(source)] if source else [])]
        out = out_root / task.name
        check_not_input(out, inputs)
        check_replaceable(out, args.overwrite)
        cache = StageCache(
            recorded.cache_root / scene if recorded.cache_root else None, writable=False
        )
        stage_one = compose_stage_one(
            task.gaussians.to(recorded.settings.device),
            task.trajectory,
            task.prompt,
            recorded.segmenter,
            recorded.vote,
            task_settings(task, recorded.settings),
            num_labels=task.num_labels,
            trajectory_gt=task.trajectory_gt,
            cache=cache,
        )
        say_what_was_redone(scene, stage_one, row)
        labels = stage_one.labels
        names = list(task.label_names or ["background"])
        names += [f"id_{i}" for i in range(len(names), stage_one.num_labels)]
        info = {
            "run": str(run),
            "scene": scene,
            "stage_keys": stage_one.keys,
            "vote": asdict(recorded.vote),
            "protocol": recorded.adapter.protocol,
        }
        write_segmentation(
            out,
            task.gaussians,
            labels,
            names[: stage_one.num_labels],
            source=Path(source) if source else None,
            info=info,
            overwrite=args.overwrite,
            inputs=inputs,
            command="export",
            on_clash="suffix",
        )
        done += 1
        labelled = f"{int((labels >= 0).sum())} of {len(labels)} Gaussians labelled"
        print(f"{scene}: {labelled} -> {shown(out)}")
    if not done:
        print(f"error: {shown(run)}: no scene of the run could be exported", file=sys.stderr)
    return 0 if done else 1


def say_what_was_redone(scene: str, stage_one, row: dict) -> None:
    """Name the stages computed again (not in the run's cache), and a vote key that differs
    from the one the run recorded (its inputs or the code changed since)."""
    redone = [name for name, r in stage_one.runs.items() if r.status == "computed"]
    if redone:
        print(
            f"note: {scene}: computed again (not in the run's cache): {', '.join(redone)}",
            file=sys.stderr,
        )
    recorded = (row.get("stage_keys") or {}).get("vote") if isinstance(row, dict) else None
    if recorded is not None and recorded != stage_one.vote.key:
        print(
            f"note: {scene}: the vote's key today ({stage_one.vote.key[:12]}) is not the one the "
            f"run recorded ({str(recorded)[:12]}): its inputs, settings or code changed since; "
            "the labels exported are today's",
            file=sys.stderr,
        )
