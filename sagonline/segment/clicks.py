"""Prompts as people give them: clicks, negative clicks and masks per named object, or texts,
all on one view, read item by item (`sagonline segment`'s --click, --object, --mask and --text,
in the order given: an --object starts a new object for what follows) or added by a viewer.
Nothing given is dropped: each item belongs to an object, or is a text. `to_prompt` turns them
into the segmenters' `Prompt`."""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sagonline.core.errors import PromptError


@dataclass
class ObjectClicks:
    """What the command line said of one object: clicks (x, y), negative clicks, a mask."""

    name: str
    points: list[tuple[float, float]] = field(default_factory=list)
    negatives: list[tuple[float, float]] = field(default_factory=list)
    mask: np.ndarray | None = None
    mask_file: str | None = None


@dataclass
class ParsedPrompt:
    """The prompt on one view: its index among the given views, the objects in order, the
    texts; `record` is what labels.json keeps of it."""

    view: int
    objects: list[ObjectClicks]
    texts: list[str]

    def record(self, cams, folder: str | Path | None = None) -> dict:
        """What labels.json keeps of the prompt; a mask file as its path relative to `folder`
        (where labels.json is written; absolute when it has no relative path from there) and
        its content digest, so a replay finds that file, and no other of the same name."""
        from sagonline.core.provenance import digest_file

        def mask(o: ObjectClicks) -> dict:
            if o.mask_file is None:
                return {"mask": None}
            path = Path(o.mask_file).absolute()
            if folder is not None:
                with contextlib.suppress(ValueError):  # no relative path (another drive)
                    path = Path(os.path.relpath(path, Path(folder).absolute()))
            return {"mask": str(path), "mask_digest": digest_file(o.mask_file)}

        return {
            "view": self.view,
            "view_name": cams[self.view].name,
            "render_size": [cams[self.view].width, cams[self.view].height],
            "objects": [
                {"name": o.name, "clicks": o.points, "negatives": o.negatives, **mask(o)}
                for o in self.objects
            ],
            "texts": self.texts,
        }


class PromptParser:
    """Reads the items one by one into objects (see the module docstring)."""

    def __init__(self, cams):
        self.cams = cams
        self.objects: dict[str, ObjectClicks] = {}
        self.texts: list[str] = []
        self.views: dict[int, str] = {}
        self.current: str | None = None

    def on_view(self, text: str, item: str) -> int:
        from sagonline.scene.views import view_index

        try:
            i = view_index(text, self.cams)
        except ValueError as exc:
            raise PromptError(f"{item}: {exc}") from None
        self.views.setdefault(i, item)
        return i

    def obj(self, name: str) -> ObjectClicks:
        return self.objects.setdefault(name, ObjectClicks(name))

    def object(self, value: str, item: str) -> None:
        if not value.strip():
            raise PromptError("--object needs a name")
        self.current = value
        self.obj(value)

    def text(self, value: str, item: str) -> None:
        if not value.strip():
            raise PromptError("--text needs words")
        self.texts.append(value)

    def mask(self, value: str, item: str) -> None:
        from sagonline.scene.io.masks import read_mask

        view, sep, path = value.partition(":")
        if not sep or not path:
            raise PromptError(f"{item}: expected VIEW:PATH")
        i = self.on_view(view, item)
        cam = self.cams[i]  # a mask is the view's size: a larger file is refused unread
        read = read_mask(path, max_pixels=cam.width * cam.height)
        if read.labels.shape != (cam.height, cam.width):
            raise PromptError(
                f"{item}: the mask is {read.labels.shape[1]}x{read.labels.shape[0]} but view "
                f"{i} ('{cam.name}') renders at {cam.width}x{cam.height}"
            )
        ids = [int(k) for k in np.unique(read.labels) if k != 0]
        if not ids:
            raise PromptError(f"{item}: the mask marks no object ({read.seen})")
        base = self.current or "object"
        for k in ids:
            name = base if len(ids) == 1 else f"{base}_{k}"
            target = self.obj(name)
            if target.mask is not None:
                raise PromptError(f"{item}: object {name!r} already has a mask")
            target.mask, target.mask_file = read.labels == k, str(path)

    def click(self, value: str, item: str) -> None:
        parts = value.split(":")
        if len(parts) not in (2, 3):
            raise PromptError(f"{item}: expected VIEW:X,Y or VIEW:X,Y:neg[=NAME]")
        i = self.on_view(parts[0], item)
        try:
            x, y = (float(v) for v in parts[1].split(","))
        except ValueError:
            raise PromptError(f"{item}: X,Y must be two numbers") from None
        cam = self.cams[i]
        if not (np.isfinite([x, y]).all() and 0 <= x < cam.width and 0 <= y < cam.height):
            raise PromptError(
                f"{item}: ({x:g}, {y:g}) is outside view {i} ('{cam.name}'), which renders at "
                f"{cam.width}x{cam.height}"
            )
        if len(parts) == 2:
            self.current = self.current or "object"
            self.obj(self.current).points.append((x, y))
            return
        flag, _, name = parts[2].partition("=")
        if flag != "neg":
            raise PromptError(f"{item}: the third part must be neg or neg=NAME")
        target = name or self.current
        if target is None:
            raise PromptError(
                f"{item}: a negative click says what an object is not: click on the object "
                "first (a positive click), or name one with :neg=NAME"
            )
        if target not in self.objects:
            raise PromptError(f"{item}: no object {target!r} to add a negative click to")
        self.objects[target].negatives.append((x, y))

    def finish(self) -> ParsedPrompt:
        if len(self.views) > 1:
            shown = ", ".join(f"{self.cams[i].name!r} ({item})" for i, item in self.views.items())
            raise PromptError(f"prompts on several views ({shown}): the segmenter takes one view")
        if self.texts and self.objects:
            raise PromptError(
                "--text names its objects itself: give either --text, or clicks and masks"
            )
        empty = [o.name for o in self.objects.values() if not o.points and o.mask is None]
        if empty:
            raise PromptError(
                f"object {empty[0]!r} has no positive click and no mask: an --object takes the "
                f"--click and --mask after it (`--object {empty[0]} --click VIEW:X,Y`); a "
                "negative click alone says what it is not"
            )
        if not self.texts and not self.objects:
            raise PromptError("no prompt: give --click, --mask or --text (or --preview VIEW)")
        return ParsedPrompt(next(iter(self.views), 0), list(self.objects.values()), self.texts)


def parse_prompt(items: list[tuple], cams) -> ParsedPrompt:
    """--click / --object / --mask / --text, in order -> the prompt. An item is (kind, value)
    or (kind, value, where): `where` names it in errors (a field of a labels.json, say),
    else `--kind value`."""
    parser = PromptParser(cams)
    for kind, value, *where in items:
        handler = getattr(parser, kind, None)
        if kind not in ("object", "text", "mask", "click") or handler is None:
            raise PromptError(f"unknown prompt item {kind!r}")
        handler(value, where[0] if where else f"--{kind} {value}")
    return parser.finish()


def to_prompt(parsed: ParsedPrompt, frame: int):
    """The segmenters' Prompt (objects labelled 1.. in order), with its label names."""
    from sagonline.segment.prompts import ObjectPrompt, Prompt

    if parsed.texts:
        return Prompt(frame=frame, texts=list(parsed.texts), names=["background", *parsed.texts])
    objects = []
    for label, o in enumerate(parsed.objects, start=1):
        pts = [*o.points, *o.negatives]
        labels = [1] * len(o.points) + [0] * len(o.negatives)
        objects.append(
            ObjectPrompt(
                label=label,
                points=np.asarray(pts, np.float64).reshape(-1, 2) if pts else None,
                point_labels=np.array(labels, np.int64) if pts else None,
                mask=o.mask,
            )
        )
    return Prompt(
        frame=frame, objects=objects, names=["background", *(o.name for o in parsed.objects)]
    )
