"""File digests: memoised across processes, remembered only while nothing can change the file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest


def _digest_many(args) -> None:
    from sagonline.core.provenance import digest_file

    folder, start = args
    for i in range(start, start + 20):
        digest_file(Path(folder) / f"f{i}.bin")


@pytest.mark.slow
def test_the_digest_memo_keeps_every_process_entries(tmp_path, monkeypatch):
    """Two processes digesting at once: the memo file holds the entries of both (it was
    rewritten without a lock, one process's entries lost)."""
    import multiprocessing as mp

    memo = tmp_path / "memo.json"
    monkeypatch.setenv("SAGONLINE_DIGEST_CACHE", str(memo))
    for i in range(40):
        (tmp_path / f"f{i}.bin").write_bytes(os.urandom(64))
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_digest_many, [(str(tmp_path), 0), (str(tmp_path), 20)])
    assert len(json.loads(memo.read_text())) == 40


def test_ground_truth_digest_is_remembered_only_while_nothing_can_change_it():
    """Read-only ground truth is hashed once per process, with the digest its bytes give;
    an array that can be written is hashed every time, so a change is always seen."""
    from sagonline.core.provenance import digest_arrays
    from sagonline.datasets.base import read_only

    frozen = [read_only(np.full((600, 600), k, np.int64)) for k in range(2)]
    copies = [a.copy() for a in frozen]
    assert digest_arrays(frozen) == digest_arrays(frozen) == digest_arrays(copies)
    writable = [np.zeros((600, 600), np.int64)]
    before = digest_arrays(writable)
    writable[0][0, 0] = 1
    assert digest_arrays(writable) != before
    with pytest.raises(ValueError, match="read-only"):
        frozen[0][0, 0] = 7


def test_label_maps_read_narrow_keep_the_digests_they_had_as_int64():
    """Masks are read at their files' 8 or 16 bits; `as_int64` hashes their values as int64,
    a block of rows at a time, so a finished run's recorded ground-truth digest still matches
    (and so does a map of more rows than one block)."""
    from sagonline.core.provenance import digest_arrays

    rng = np.random.default_rng(0)
    maps = [
        rng.integers(0, 3, (24, 31)).astype(np.uint8),
        rng.integers(0, 60000, (2100, 700)).astype(np.uint16),  # 3 blocks of rows
        rng.integers(0, 2, (5,)).astype(np.uint8),
    ]
    wide = [m.astype(np.int64) for m in maps]
    assert digest_arrays(maps, as_int64=True) == digest_arrays(wide)
    assert digest_arrays(maps, as_int64=True) != digest_arrays(maps)
    frames = [rng.integers(0, 255, (4, 4, 3)).astype(np.float32)]  # not integers: as they are
    assert digest_arrays(frames, as_int64=True) == digest_arrays(frames)
    for m in maps:  # the read-only ground truth is remembered apart from its plain digest
        m.flags.writeable = False
    assert digest_arrays(maps) != digest_arrays(maps, as_int64=True) == digest_arrays(wide)


PY = '''"""A module."""

import math


def area(r):
    """The disc's area."""
    return math.pi * r * r  # pi r squared
'''
CPP = """// A kernel.
#include <cmath>
/* the area
   of a disc */
float area(float r) { return 3.14159f * r * r; }  // pi r squared
const char* name() { return "a // not a comment /* nor this */"; }
"""


@pytest.mark.parametrize(
    "suffix, text, same, other",
    [
        (
            ".py",
            PY,
            PY.replace('"""The disc\'s area."""', "# the area\n    # of a disc").replace(
                "\n\n\ndef", "\n\n\n\ndef"
            ),
            PY.replace("r * r", "r ** 2"),
        ),
        (
            ".cpp",
            CPP,
            CPP.replace("// A kernel.", "// A kernel, said otherwise.\n\n").replace(
                "of a disc */", "of a circle */   "
            ),
            CPP.replace("/* nor this */", "/* nor that */"),
        ),
    ],
)
def test_a_sources_digest_reads_its_code_not_its_comments(tmp_path, suffix, text, same, other):
    """The implementation digest in every render stage's key (`render.backends`) reads each
    source's code: a comment, a docstring or a blank line moves nothing; a change to the code
    (or to a string literal that looks like a comment) does."""
    from sagonline.core.provenance import source_code

    def code(source: str) -> bytes:
        path = tmp_path / f"kernel{suffix}"
        path.write_text(source)
        return source_code(path)

    assert code(same) == code(text) and same != text
    assert code(other) != code(text)
