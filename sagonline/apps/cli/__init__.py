"""Command line: `sagonline info | cameras | render | segment | view | figure | export | score |
plugins`.

    sagonline info SCENE                      format, Gaussian count, SH degree, bounds
    sagonline cameras CAMERAS                 every view's index, name and size
    sagonline render SCENE --cameras C --view VIEW --out view.png
    sagonline segment SCENE [--cameras C] --click VIEW:X,Y [--object NAME] ...
    sagonline segment SCENE --prompts SEGMENT_DIR/labels.json   a segmentation again, no browser
    sagonline view SCENE [--cameras C]        click in the browser, watch the labels form, export
    sagonline figure SEGMENT_DIR --out x.png  render | labels | each object alone, titled
    sagonline export RUN_DIR                  a finished eval run's labels, per scene
    sagonline score RUN_DIR | PRED_DIR GT_DIR  label maps re-scored by the harness's rules
    sagonline plugins [segmenters|datasets|vote-rules]

Every problem with an input ends in one line that names the file, flag or setting, and a
non-zero exit status; nothing outside `--out` is ever written (`sagonline.core.outputs`).
"""

from __future__ import annotations

import argparse
import os
import sys

# How every command that renders names a view and a pixel (`scene.views`, `segment.clicks`)
CLICK_HELP = (
    "VIEW is an index in `sagonline cameras` (cameras sorted by name) or a camera's name; X,Y "
    "are pixels of that view at its render size (--width/--height, else the camera's own), x "
    "right, y down, from the top-left corner"
)


# Each command: the module of this package that declares it, and its line in `--help`
COMMANDS = {
    "info": ("inspect", "format, Gaussian count, SH degree, bounding box"),
    "cameras": (
        "inspect",
        "every view's index, name and size, in the order every command numbers them",
    ),
    "plugins": ("inspect", "the registered segmenters, datasets, vote rules"),
    "render": ("render", "render one view to PNG or .npy (float32 HxWx3)"),
    "segment": (
        "segment",
        "segment a scene from clicks, masks or text; write labels, object PLYs, renders",
    ),
    "view": ("view", "segment a scene in the browser: click, watch the labels form, export"),
    "figure": ("figure", "a picture of a segment folder: render | labels | each object alone"),
    "export": ("export", "a finished eval run's labels as files (per scene)"),
    "score": ("score", "re-score label maps (a run's, or a peer's) by our rules"),
}


def command_parser(sub, name: str) -> argparse.ArgumentParser:
    """The sub-parser of command `name`, with its line from COMMANDS."""
    return sub.add_parser(name, help=COMMANDS[name][1])


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The command line's parser. With `argv`, only the module of the command it names is
    imported, the others' commands are listed by name and line: `sagonline --help`, a typo
    in a command's name and `sagonline info --help` need no PyTorch (about 2 s)."""
    import importlib

    parser = argparse.ArgumentParser(
        prog="sagonline",
        description="Segment any Gaussians online: inspect, render, segment and export scenes.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    named = next((a for a in argv if not a.startswith("-")), None) if argv is not None else None
    wanted = {COMMANDS[named][0]} if named in COMMANDS else set()
    for module in dict.fromkeys(m for m, _ in COMMANDS.values()):
        if argv is None or module in wanted:
            importlib.import_module(f"sagonline.apps.cli.{module}").add_parsers(sub)
        else:
            for name in (c for c, (m, _) in COMMANDS.items() if m == module):
                command_parser(sub, name)
    return parser


# Options whose value may begin with "-" (a view of -1 is refused by its own rule, naming it,
# instead of argparse's "expected one argument").
DASHED_VALUES = ("--click", "--mask", "--preview", "--view")


def joined_values(argv: list[str]) -> list[str]:
    """`--click -1:10,10` as `--click=-1:10,10`, so argparse reads the value as one."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in DASHED_VALUES and i + 1 < len(argv) and argv[i + 1].startswith("-"):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit status (0: done, 2: a problem with the input, 1: an
    unexpected failure, 130: interrupted, 141: its output's reader went away).
    SAGONLINE_DEBUG=1 shows the traceback of an unexpected failure."""
    import warnings

    from sagonline.core.errors import DatasetError, NativeBuildError

    # the library's warnings are said as one line each, not with the source line that raised them
    warnings.formatwarning = lambda message, category, *_, **__: (
        f"warning: {message}\n" if issubclass(category, UserWarning) else f"{message}\n"
    )
    try:
        argv = joined_values(sys.argv[1:] if argv is None else argv)
        args = build_parser(argv).parse_args(argv)
        status = args.func(args)
        sys.stdout.flush()  # a reader that went away is met here, not at the interpreter's exit
        return status
    except BrokenPipeError:  # `sagonline cameras X | head`: the reader has what it wanted
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # for the exit's flush
        return 141  # as a shell reports a writer its pipe's SIGPIPE ended
    except KeyboardInterrupt:
        print("interrupted: nothing was left half-written", file=sys.stderr)
        return 130
    except (ValueError, DatasetError, OSError, MemoryError, NativeBuildError) as exc:
        if os.environ.get("SAGONLINE_DEBUG"):
            raise
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # a bug: still one line, with the way to see more
        if os.environ.get("SAGONLINE_DEBUG"):
            raise
        print(
            f"error: unexpected {type(exc).__name__}: {one_line(exc)} (a bug: rerun with "
            "SAGONLINE_DEBUG=1 for the traceback, and report it)",
            file=sys.stderr,
        )
        return 1


def one_line(exc: BaseException) -> str:
    """An error's message on one line."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    if isinstance(exc, MemoryError):
        text = f"out of memory ({text or 'no detail'}); try a smaller size or fewer views"
    return " ".join(text.split()) or type(exc).__name__


__all__ = ["build_parser", "main"]
