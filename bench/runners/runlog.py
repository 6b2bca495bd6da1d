"""The run's log: `<run dir>/eval.log` receives every record and warning of the run."""

from __future__ import annotations

import logging
import sys
from contextlib import contextmanager
from pathlib import Path


def _not_file_only(record: logging.LogRecord) -> bool:
    return not getattr(record, "file_only", False)


@contextmanager
def run_log(out_dir: Path):
    """`<run dir>/eval.log` receives every log record and warning of the run; warnings also
    reach the console (records logged with `extra=FILE_ONLY` stay out of it)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    root = logging.getLogger()
    consoles = list(root.handlers)
    for h in consoles:
        h.addFilter(_not_file_only)
    file_handler = logging.FileHandler(out_dir / "eval.log")
    file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handlers = [file_handler]
    if not root.handlers:
        console = logging.StreamHandler(sys.stderr)
        console.setLevel(logging.WARNING)
        console.setFormatter(logging.Formatter("%(levelname)s: %(message)s"))
        console.addFilter(_not_file_only)
        handlers.append(console)
    old_level = root.level
    root.setLevel(logging.INFO)
    for h in handlers:
        root.addHandler(h)
    logging.captureWarnings(True)
    try:
        yield
    finally:
        logging.captureWarnings(False)
        for h in handlers:
            root.removeHandler(h)
            h.close()
        for h in consoles:
            h.removeFilter(_not_file_only)
        root.setLevel(old_level)


def disk_words(exc: OSError) -> str:
    """An OSError of writing, as one line naming the file or folder and what to do."""
    import errno

    where = exc.filename or "a file of the run"
    why = exc.strerror or str(exc)
    hint = {
        errno.ENOSPC: "free some space (make clean-cache empties the stage cache) and rerun: "
        "the finished stages are kept",
        errno.EFBIG: "a file size limit (ulimit -f) stopped the write; raise it and rerun",
        errno.EROFS: "the disk is read-only; choose another folder",
        errno.EACCES: "fix the folder's permissions or choose another",
    }.get(exc.errno, "")
    return f"cannot write {where}: {why}" + (f"; {hint}" if hint else "")
