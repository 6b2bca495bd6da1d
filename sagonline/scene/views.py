"""Which views a command works on, in one numbering for every command.

A camera file's views are numbered in one documented order: **sorted by camera name** (the
pseudo-temporal order of the harness's trajectories). `sagonline cameras PATH` prints that
numbering; `render --view`, `segment --click VIEW:X,Y` and `segment --preview VIEW` all take an
index in it, or a camera's name; from Python, `load_views` gives the same list. With
`--orbit N` the views are a ring of N views instead (around the scene from the first camera,
or, for a scene without cameras, around its bounds; `--inside`: from its centre looking out,
for a room seen from within), numbered in ring order.

`segment --every N` and `view --every N` render and segment views 0, N, 2N, ... only (and
the prompt's view: `segmented_views`); those keep their numbers and names.

Clicks are pixels of the view **at its render size** (`--width`/`--height`, else the
camera's own size): x to the right, y down, origin at the top-left corner.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from sagonline.scene.cameras import Camera
from sagonline.scene.gaussians import Gaussians

# Ceilings that name themselves: every view is rendered and held in memory.
MAX_ORBIT = int(os.environ.get("SAGONLINE_MAX_ORBIT", 720))
MAX_TRAJECTORY = int(os.environ.get("SAGONLINE_MAX_TRAJECTORY", 2000))
DEFAULT_ORBIT = 24


class ViewError(ValueError):
    """A view, a size or an orbit that the cameras cannot give; says which and why."""


@dataclass
class Views:
    """The views a command works on (documented order), and where they came from."""

    cameras: list[Camera]
    source: str


def load_views(
    cameras: str | Path | None,
    gaussians: Gaussians | None = None,
    *,
    orbit: int = 0,
    width: int | None = None,
    height: int | None = None,
    inside: bool = False,
) -> Views:
    """The views: the camera file's, sorted by name (or a ring of `orbit` views from its first
    camera); without a camera file, a ring around the scene's bounds (`orbit`, default 24),
    or, `inside`, a turn from the scene's centre looking out (a room seen from within).
    Rescaled to width x height when given."""
    from sagonline.scene.io.cameras import load_cameras
    from sagonline.scene.trajectory import orbit_around, pseudo_temporal_order, ring_around

    if (width is None) != (height is None):
        raise ViewError("give both --width and --height, or neither")
    if orbit < 0 or orbit == 1 or orbit > MAX_ORBIT:
        raise ViewError(
            f"--orbit {orbit}: takes 2 to {MAX_ORBIT} views (sagonline.scene.views.MAX_ORBIT; "
            "the environment variable SAGONLINE_MAX_ORBIT raises it)"
        )
    if cameras is None:
        if gaussians is None:
            raise ViewError("no --cameras given and no scene to place an orbit around")
        count = orbit or DEFAULT_ORBIT
        cams, line = orbit_around(
            gaussians.means, count, width or 640, height or 480, inside=inside
        )
        return Views(cams, f"no --cameras given: {line}")
    if inside:
        raise ViewError(
            "--inside places views in a scene without cameras; with --cameras the views are "
            "the camera file's (or --orbit N around the scene from its first camera)"
        )
    cams = pseudo_temporal_order(load_cameras(cameras))
    if not cams:
        raise ViewError(f"{cameras}: holds no cameras (no images in the model?)")
    count = f"{len(cams)} camera{'' if len(cams) == 1 else 's'}"
    source = f"{count} of {cameras}{sized_by_images(cameras)}, sorted by name"
    if orbit:
        if gaussians is None:
            raise ViewError("--orbit needs the scene")
        centre = gaussians.means.detach().float().median(dim=0).values.cpu().numpy()
        first = cams[0]
        cams = ring_around(first, centre, orbit)
        source = (
            f"an orbit of {orbit} views (orbit_000..orbit_{orbit - 1:03d}, numbered along the "
            f"ring: --orbit replaces the camera file's numbering) around the scene, starting "
            f"at the camera file's first camera {first.name!r}"
        )
    if width is not None:
        try:
            cams = [c.scaled(width, height) for c in cams]
        except ValueError as exc:
            raise ViewError(f"--width {width} --height {height}: {exc}") from None
    return Views(cams, source)


def sized_by_images(cameras: str | Path) -> str:
    """The views line's ', sized and named by the images of its images_8/' where LLFF poses
    took their size and names from a folder beside them (`cameras.llff_image_folder`), else
    nothing."""
    from sagonline.scene.io.cameras import llff_image_folder

    folder = llff_image_folder(cameras)
    return f", sized and named by the images of its {folder.name}/" if folder else ""


def view_index(text: str, cams: list[Camera]) -> int:
    """A VIEW (an index in the documented order, or a camera's name) -> its index."""
    names = [c.name for c in cams]
    text = str(text).strip()
    if text in names:
        return names.index(text)
    if text.lstrip("-").isdigit():
        i = int(text)
        if not 0 <= i < len(cams):
            raise ViewError(
                f"view {i} is out of range: there are {len(cams)} views (0..{len(cams) - 1}; "
                "`sagonline cameras` lists them)"
            )
        return i
    shown = f"{names[0]} ... {names[-1]}" if len(names) > 1 else names[0]
    raise ViewError(f"no view named {text!r} (views: {shown}; `sagonline cameras` lists them)")


def check_every(every: int | None) -> int:
    """--every as a number of views: None (not given) is 1, every view; below 1 is refused."""
    if every is None:
        return 1
    if every < 1:
        raise ViewError(f"--every {every}: must be 1 (every view) or more")
    return every


def segmented_views(cams: list[Camera], every: int = 1, keep: int = 0) -> list[Camera]:
    """The views a segmenter watches: every `every`-th of `cams` (0, every, 2 every, ...) and
    cams[keep] (the prompt's view), in their order; the others are neither rendered nor
    segmented. Each keeps its name, so clicks and files keep `sagonline cameras`' numbering."""
    check_every(every)
    if not 0 <= keep < len(cams):
        raise ViewError(f"view {keep} is out of range: there are {len(cams)} views")
    return [c for i, c in enumerate(cams) if i % every == 0 or i == keep]


def trajectory(
    cams: list[Camera], *, every: int = 1, keep: int = 0, inbetween: int = 0
) -> list[Camera]:
    """What `segment` renders, segments and votes from, and what `figure` rebuilds from a
    segment folder's labels.json: `segmented_views`, then `inbetween` views slerped between
    each consecutive pair (`trajectory.insert_between`)."""
    from sagonline.scene.trajectory import insert_between

    return insert_between(segmented_views(cams, every, keep), inbetween)


def every_line(cams: list[Camera], every: int, keep: int, length: int | None = None) -> str:
    """'50 of 198 views (every 4th, and the prompt's view 7)', '198 views' for every view;
    with the trajectory's `length`, the views slerped in between too ('... and 49 in between')."""
    picked = len(segmented_views(cams, every, keep))
    line = f"{len(cams)} view" + ("" if len(cams) == 1 else "s")
    if every > 1:
        extra = f", and the prompt's view {keep}" if keep % every else ""
        line = f"{picked} of {len(cams)} views (every {ordinal(every)}{extra})"
    if length is not None and length > picked:
        line += f" and {length - picked} in between"
    return line


def ordinal(n: int) -> str:
    """2 -> '2nd', 11 -> '11th', 23 -> '23rd'."""
    last = "th" if n % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{last}"


def check_trajectory(cams: list[Camera]) -> None:
    if len(cams) > MAX_TRAJECTORY:
        raise ViewError(
            f"{len(cams)} views exceed the ceiling of {MAX_TRAJECTORY} for one trajectory "
            "(sagonline.scene.views.MAX_TRAJECTORY; SAGONLINE_MAX_TRAJECTORY raises it): every "
            "view is rendered and kept in memory"
        )


__all__ = [
    "MAX_ORBIT",
    "MAX_TRAJECTORY",
    "ViewError",
    "Views",
    "check_every",
    "load_views",
    "segmented_views",
    "trajectory",
]
