"""Checkpoints the user hands in (SAM 2, SAM 3, a pretrained encoder): opened so that nothing in
them runs.

`torch.load(..., weights_only=True)` rebuilds tensors and plain containers only. A file that
needs arbitrary unpickling (Python objects, which can run any code while loading) is refused
with `UntrustedCheckpoint`, which says why and names the opt-in setting for a file the user
trusts. The harness's own files (caches, fit and student checkpoints) never use pickle at all:
`sagonline.core.store`.
"""

from __future__ import annotations

import pickle
import re
from pathlib import Path

import torch


class UntrustedCheckpoint(ValueError):
    """A checkpoint that only arbitrary unpickling can load; the message names the opt-in."""


def unsafe_reason(exc: BaseException) -> str:
    """The part of torch's weights_only refusal that says what the file asked for."""
    text = str(exc)
    found = re.search(
        r"(Unsupported global: [^\n]*|[^\n]*unsupported GLOBAL [^\n]*|Unsupported operand[^\n]*)",
        text,
    )
    return found.group(1).strip().rstrip(".") if found else text.splitlines()[0][:200]


def refuse_untrusted(option: str, path: Path, why: str, trust_option: str | None) -> None:
    opt_in = (
        f" If you trust this file, pass {trust_option}=true."
        if trust_option
        else " Convert it to a plain state dict (torch.save(model.state_dict(), path))."
    )
    raise UntrustedCheckpoint(
        f"{option}={path}: refused: loading it needs arbitrary unpickling ({why}), which can run "
        f"code stored in the file.{opt_in}"
    )


def load_user_checkpoint(
    path: str | Path, option: str, *, trust: bool = False, trust_option: str | None = None
):
    """torch.load of a file named by the setting `option`: weights_only unless `trust` (the
    user's opt-in `trust_option`). Raises FileNotFoundError, UntrustedCheckpoint, or ValueError
    for a file that is not a readable checkpoint, each naming the option and the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{option}={path}: no such file")
    try:
        return torch.load(path, map_location="cpu", weights_only=not trust)
    except pickle.UnpicklingError as exc:
        if re.search(r"unsupported GLOBAL|Unsupported global", str(exc)):
            refuse_untrusted(option, path, unsafe_reason(exc), trust_option)
        raise ValueError(
            f"{option}={path}: not a readable PyTorch checkpoint ({unsafe_reason(exc)})"
        ) from None
    except Exception as exc:  # weights_only parsing runs no code: any failure is a bad file
        raise ValueError(
            f"{option}={path}: not a readable PyTorch checkpoint "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
