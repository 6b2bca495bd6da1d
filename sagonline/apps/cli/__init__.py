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


def build_parser() -> argparse.ArgumentParser:
    from sagonline.apps.cli import export, figure, inspect, render, score, segment, view

    parser = argparse.ArgumentParser(
        prog="sagonline",
        description="Segment any Gaussians online: inspect, render, segment and export scenes.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for module in (inspect, render, segment, view, figure, export, score):
        module.add_parsers(sub)
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

    from sagonline.core.errors import DatasetError
    from sagonline.render.kernels import NativeBuildError

    # the library's warnings are said as one line each, not with the source line that raised them
    warnings.formatwarning = lambda message, category, *_, **__: (
        f"warning: {message}\n" if issubclass(category, UserWarning) else f"{message}\n"
    )
    try:
        args = build_parser().parse_args(joined_values(sys.argv[1:] if argv is None else argv))
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
