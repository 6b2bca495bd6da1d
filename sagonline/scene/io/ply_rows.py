"""PLY headers parsed by hand and vertex rows read in bounded blocks: the declared rows are
checked against the file's size before anything is allocated, so a damaged header cannot ask for
terabytes. ASCII files (and binary ones with list properties before the vertices) go through
plyfile."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData

from sagonline.core.errors import SceneFileError

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
_MAX_HEADER = 1 << 20
BLOCK_ROWS = 1 << 14


@dataclass
class PlyElementHeader:
    """One element of a PLY header: name, row count, and (name, type) properties (a list
    property's type is 'list')."""

    name: str
    count: int
    properties: list[tuple[str, str]]


@dataclass
class PlyHeader:
    format: str  # ascii | binary_little_endian | binary_big_endian
    elements: list[PlyElementHeader]
    size: int  # bytes, up to and including the end_header line


def read_ply_header(path: Path) -> PlyHeader:
    """Parse a PLY header (at most 1 MiB); a malformed one raises SceneFileError naming it."""
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER)
    end = head.find(b"end_header")
    line_end = head.find(b"\n", end) if end >= 0 else -1
    if not head.startswith(b"ply") or end < 0 or line_end < 0:
        raise SceneFileError(f"{path}: not a readable PLY file (no 'ply' ... 'end_header' header)")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise SceneFileError(f"{path}: not a readable PLY file (non-ASCII header)") from None
    fmt, elements = None, []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
                if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
                    raise ValueError(f"unknown format {fmt!r}")
            elif words[0] == "element":
                count = int(words[2])
                if count < 0 or len(words) != 3:
                    raise ValueError("an element needs a name and a count >= 0")
                elements.append(PlyElementHeader(words[1], count, []))
            elif words[0] == "property":
                if not elements:
                    raise ValueError("a property before any element")
                if words[1] == "list":
                    elements[-1].properties.append((words[4], "list"))
                elif words[1] in _PLY_TYPES and len(words) == 3:
                    elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
                else:
                    raise ValueError(f"unknown property type {words[1]!r}")
            else:
                raise ValueError(f"unknown keyword {words[0]!r}")
        except (ValueError, IndexError) as exc:
            raise SceneFileError(
                f"{path}: not a readable PLY file (header line {number}: {line!r}: {exc})"
            ) from None
    if fmt is None:
        raise SceneFileError(f"{path}: not a readable PLY file (no 'format' line)")
    for element in elements:
        names = [n for n, _ in element.properties]
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise SceneFileError(
                f"{path}: not a readable PLY file (element {element.name!r} repeats "
                f"properties {repeated})"
            )
    return PlyHeader(fmt, elements, line_end + 1)


def vertex_blocks(path: Path, header: PlyHeader, vertex: PlyElementHeader):
    """An iterator of (first row, structured block) pairs over the vertex element,
    `BLOCK_ROWS` at a time, after checking (before anything is allocated) that the declared
    rows fit the file. Binary files are read straight from disk; ASCII files (and binary ones
    with list properties before the vertices) go through plyfile."""
    size = path.stat().st_size
    before = header.elements[: header.elements.index(vertex)]
    fixed = all(t != "list" for e in [*before, vertex] for _, t in e.properties)
    if header.format != "ascii" and fixed:
        order = "<" if header.format == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in vertex.properties])
        offset = header.size + sum(
            e.count * np.dtype([(n, order + t) for n, t in e.properties]).itemsize for e in before
        )
        need = vertex.count * dtype.itemsize
        if offset + need > size:
            raise SceneFileError(
                f"{path}: truncated: the header declares {vertex.count} vertices "
                f"({need:,} bytes from byte {offset:,}) but the file has {size:,} bytes"
            )
        return _binary_blocks(path, dtype, offset, vertex.count)
    # An ASCII row takes at least two bytes per value: a count the file cannot hold is refused
    # before plyfile allocates for it.
    if sum(e.count * max(len(e.properties), 1) * 2 for e in [*before, vertex]) > size:
        raise SceneFileError(
            f"{path}: truncated: the header declares {vertex.count} vertices, more than the "
            f"file's {size:,} bytes can hold"
        )
    try:
        data = PlyData.read(str(path))["vertex"].data
    except Exception as exc:  # plyfile raises several types for truncated/garbled input
        raise SceneFileError(
            f"{path}: not a readable PLY file ({type(exc).__name__}: {exc})"
        ) from exc
    if len(data) != vertex.count:
        raise SceneFileError(
            f"{path}: {len(data)} vertices read, the header declares {vertex.count}"
        )
    return ((start, data[start : start + BLOCK_ROWS]) for start in range(0, len(data), BLOCK_ROWS))


def _binary_blocks(path: Path, dtype: np.dtype, offset: int, count: int):
    with open(path, "rb") as f:
        f.seek(offset)
        for start in range(0, count, BLOCK_ROWS):
            yield start, np.fromfile(f, dtype=dtype, count=min(BLOCK_ROWS, count - start))
