"""`sagonline segment --prompts labels.json`: a recorded segmentation's prompt, views, segmenter
and vote read back, every field checked (one line naming the file and the field), its mask
found where labels.json says and checked to be the file that was recorded."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from sagonline.apps.cli.render import NO_CAMERAS
from sagonline.core.errors import PromptError


@dataclass(frozen=True)
class Replay:
    """What a --prompts labels.json gives besides the command line's own options: the vote's
    recorded settings (VoteConfig's names; what the command line gives wins), the label
    renders' min_weight, the scene's digest and the weights the segmenter ran with (compared
    with this machine's, and said)."""

    path: Path
    vote: dict = field(default_factory=dict)
    min_weight: float | None = None
    scene: str = ""
    weights: list[dict] | None = None


def apply_recorded_prompts(args) -> Replay:
    """--prompts labels.json: its prompt becomes the prompt items, and its views and segmenter
    the defaults of whatever the command line left out; the rest is returned as a `Replay`.
    Every field is checked (a wrong type or value stops with one line naming the file and the
    field); a recorded mask is read from where labels.json says, relative to labels.json, and
    must still be the file that was recorded (its content digest)."""
    from sagonline.core.files import read_json_object
    from sagonline.vote.consensus import VoteConfig

    path = Path(args.prompts)
    if args.prompt_items:
        raise PromptError(
            "--prompts replaces --click/--object/--mask/--text: give one or the other"
        )
    record = read_json_object(path, PromptError, "not readable JSON", "a labels.json (an object)")
    field = RecordFields(path, record)
    prompt = field.get("prompt", dict)
    view = field.get("prompt.view_name", str, prompt.get("view_name"))
    args.prompt_items = recorded_items(field, prompt, view)
    if args.cameras is None and not args.orbit and record.get("cameras"):
        args.cameras = recorded_cameras(field, record, args.scene)
    elif args.cameras is None and "cameras" in record and record["cameras"] is None:
        args.cameras = NO_CAMERAS  # recorded without cameras: its orbit, not any found beside
    if not args.orbit and record.get("orbit"):
        args.orbit = field.get("orbit", int)
    if not getattr(args, "inside", False) and record.get("inside"):
        args.inside = field.get("inside", bool)
    if args.width is None and prompt.get("render_size"):
        size = field.get("prompt.render_size", list, prompt["render_size"])
        if len(size) != 2:
            raise PromptError(f"{path}: prompt.render_size must be [width, height]")
        args.width, args.height = (field.check("prompt.render_size", v, int) for v in size)
    if not args.inbetween and record.get("inbetween"):
        args.inbetween = field.get("inbetween", int)
    if args.every is None and record.get("every") is not None:
        args.every = field.get("every", int)
        if args.every < 1:
            raise PromptError(f"{path}: every must be 1 (every view) or more, found {args.every}")
    weights = apply_recorded_segmenter(args, field, record)
    vote = field.get("vote", dict, record.get("vote") or {})
    known = VoteConfig.__dataclass_fields__
    unknown = sorted(set(vote) - set(known))
    if unknown:
        raise PromptError(f"{path}: vote settings {unknown} are not VoteConfig's")
    for key, value in vote.items():  # the types VoteConfig's fields hold
        default = known[key].default
        kinds = (int, float) if isinstance(default, float) or key == "delta" else type(default)
        if not (value is None and key in ("delta", "num_masks")):
            field.check(f"vote.{key}", value, kinds)
    label_render = field.get("label_render", dict, record.get("label_render") or {})
    weight = None
    if "min_weight" in label_render:
        weight = label_render["min_weight"]
        weight = field.check("label_render.min_weight", weight, (int, float))
    inputs = field.get("inputs", dict, record.get("inputs") or {})
    scene = field.check("inputs.scene", inputs.get("scene", ""), str)
    replay = Replay(path, vote, weight, scene, weights)
    from sagonline.scene.io import scene_file

    say_if_another_scene(replay, scene_file(args.scene))
    return replay


def recorded_cameras(field: RecordFields, record: dict, scene: str) -> str:
    """labels.json's camera file where it is; else (the relative path of a folder written
    before paths were recorded absolute, replayed from another folder) the camera file beside
    `scene` whose digests labels.json records (`inputs`); else refused, naming --cameras."""
    from sagonline.scene.io import scene_file
    from sagonline.scene.io.cameras import camera_digests, cameras_beside

    recorded = field.get("cameras", str)
    if Path(recorded).exists():
        return recorded
    beside = cameras_beside(scene_file(scene))
    inputs = record.get("inputs") if isinstance(record.get("inputs"), dict) else {}
    digests = camera_digests(beside) if beside is not None else {}
    if digests and all(inputs.get(name) == digest for name, digest in digests.items()):
        print(
            f"note: {field.path}: its camera file {recorded} is not here; the same file lies "
            f"beside the scene: {beside}",
            file=sys.stderr,
        )
        return str(beside)
    raise PromptError(
        f"{field.path}: its camera file {recorded} is not here (a path relative to the folder "
        "it was made in?); pass --cameras naming it"
    )


def recorded_items(field: RecordFields, prompt: dict, view: str) -> list[tuple]:
    """The recorded texts, objects, clicks and masks as the command line's prompt items (two
    objects of one name are refused: they would be merged)."""
    path = field.path
    texts = field.get("prompt.texts", list, prompt.get("texts", []))
    items = [
        ("text", field.check(f"prompt.texts[{i}]", t, str), f"{path}: prompt.texts[{i}]")
        for i, t in enumerate(texts)
    ]
    objects = field.get("prompt.objects", list, prompt.get("objects", []))
    seen: dict[str, int] = {}
    for i, obj in enumerate(objects):
        where = f"prompt.objects[{i}]"
        obj = field.check(where, obj, dict)
        name = field.check(f"{where}.name", obj.get("name"), str)
        if name in seen:
            raise PromptError(
                f"{path}: {where}.name {name!r} is prompt.objects[{seen[name]}]'s "
                "too: two objects need two names"
            )
        seen[name] = i
        items.append(("object", name, f"{path}: {where}.name"))
        for kind in ("clicks", "negatives"):
            for j, xy in enumerate(field.check(f"{where}.{kind}", obj.get(kind, []), list)):
                x, y = field.point(f"{where}.{kind}[{j}]", xy)
                value = f"{view}:{x!r},{y!r}" + (f":neg={name}" if kind == "negatives" else "")
                items.append(("click", value, f"{path}: {where}.{kind}[{j}]"))
        if obj.get("mask") is not None:
            mask = field.mask(where, obj)
            items.append(("mask", f"{view}:{mask}", f"{path}: {where}.mask ({mask})"))
    return items


def apply_recorded_segmenter(args, field: RecordFields, record: dict) -> list[dict] | None:
    """The recorded segmenter where the command line names none: its kind and the options a
    replay takes (`replayed_options`); returns the weights it ran with (compared once built;
    None where the command line names its own segmenter)."""
    path = field.path
    segmenter = field.get("segmenter", dict, record.get("segmenter") or {})
    if args.segmenter is None and segmenter.get("kind"):
        args.segmenter = field.get("segmenter.kind", str, segmenter["kind"])
        options = field.get("segmenter.options", list, segmenter.get("options", []))
        options = [field.check(f"segmenter.options[{i}]", o, str) for i, o in enumerate(options)]
        args.segmenter_option = [*replayed_options(path, options), *args.segmenter_option]
        weights = field.get("segmenter.weights", list, segmenter.get("weights") or [])
        return [field.weights(f"segmenter.weights[{i}]", w) for i, w in enumerate(weights)]
    return None


LOCAL_SETTINGS = frozenset(
    {
        "checkpoint",
        "config",
        "weights",
        "model_yaml",
        "bpe_path",
        "tracker",
        "encoder",
        "decoder",
        "embedding_cache",
        "embedding_cache_gb",
        "threads",
        "device",
        "trust_checkpoint",
        "allow_random_weights",
    }
)
"""Segmenter settings a replay never takes from a file: which files this machine loads or
writes, how many threads it starts and where it runs are this machine's to say (the command
line's --checkpoint / --segmenter-option give them)."""


def replayed_options(path: Path, options: list[str]) -> list[str]:
    """The recorded segmenter options a replay takes: every KEY=VALUE but LOCAL_SETTINGS',
    which are left out and said (their values are checked by the segmenter's config)."""
    kept, left = [], []
    for option in options:
        key, sep, _ = option.partition("=")
        if not sep:
            raise PromptError(f"{path}: segmenter.options item {option!r} is not KEY=VALUE")
        (left if key.strip() in LOCAL_SETTINGS else kept).append(option)
    if left:
        print(
            f"note: --prompts {path}: its segmenter options {', '.join(left)} name files, "
            "threads or a device of the machine that wrote it; this machine's own are used "
            "(give them with --segmenter-option or --checkpoint)",
            file=sys.stderr,
        )
    return kept


def say_if_other_weights(replay: Replay, segmenter) -> None:
    """A labels.json recorded with other weights (another sha256 for a file of the same role):
    replayed with this machine's, and said."""
    recorded = {Path(w["path"]).name: w["sha256"] for w in replay.weights or []}
    here = {Path(w["path"]).name: w["sha256"] for w in segmenter.weights_record()}
    other = sorted(name for name in recorded.keys() & here.keys() if recorded[name] != here[name])
    gone = sorted(set(recorded) - set(here))
    if other or gone:
        said = [f"{n} (recorded {recorded[n][:12]}..., here {here[n][:12]}...)" for n in other]
        said += [f"{n} (recorded, not used here)" for n in gone]
        print(
            f"note: --prompts {replay.path} was recorded with other weights: "
            f"{'; '.join(said)}; its masks may differ from the recorded run's",
            file=sys.stderr,
        )


def say_if_another_scene(replay: Replay, scene: Path) -> None:
    """A labels.json recorded on another scene (its scene's digest differs): replayed, and
    said (a scene fitted again from the same capture is a fair reason to replay)."""
    from sagonline.core.provenance import digest_file

    recorded = replay.scene
    if recorded and recorded != digest_file(scene):
        print(
            f"note: --prompts {replay.path} was recorded on another scene (SHA-256 "
            f"{str(recorded)[:12]}..., this one {digest_file(scene)[:12]}...): its clicks are "
            "replayed on this one",
            file=sys.stderr,
        )


class RecordFields:
    """The fields of a labels.json, each checked for its type, every refusal one line naming
    the file and the field (`field` with its path, e.g. prompt.objects[0].clicks[1])."""

    def __init__(self, path: Path, record: dict):
        self.path, self.record = path, record

    def check(self, field: str, value, kinds):
        ok = isinstance(value, kinds) and not (isinstance(value, bool) and kinds is not bool)
        if not ok:
            names = " or ".join(
                k.__name__ for k in (kinds if isinstance(kinds, tuple) else (kinds,))
            )
            raise PromptError(
                f"{self.path}: {field} must be {names}, found {value!r} ({type(value).__name__})"
            )
        return value

    def get(self, field: str, kinds, value=None):
        return self.check(field, self.record.get(field) if value is None else value, kinds)

    def point(self, field: str, xy) -> tuple[float, float]:
        import math

        if not (isinstance(xy, list) and len(xy) == 2):
            raise PromptError(f"{self.path}: {field} must be [x, y], found {xy!r}")
        x, y = (float(self.check(field, v, (int, float))) for v in xy)
        if not (math.isfinite(x) and math.isfinite(y)):
            raise PromptError(f"{self.path}: {field} must be finite, found {xy!r}")
        return x, y

    def weights(self, field: str, value) -> dict:
        """One recorded weights file: {"path": str, "sha256": 64 hex digits}."""
        item = self.check(field, value, dict)
        path = self.check(f"{field}.path", item.get("path"), str)
        digest = self.check(f"{field}.sha256", item.get("sha256"), str)
        if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
            raise PromptError(
                f"{self.path}: {field}.sha256 must be 64 hex digits, found {digest!r}"
            )
        return {"path": path, "sha256": digest}

    def mask(self, where: str, obj: dict) -> Path:
        """The recorded mask: relative to labels.json, the file that was recorded."""
        from sagonline.core.provenance import digest_file

        given = Path(self.check(f"{where}.mask", obj["mask"], str))
        mask = given if given.is_absolute() else self.path.parent / given
        if not mask.is_file():
            raise PromptError(f"{self.path}: {where}.mask {given} is not there ({mask})")
        recorded = obj.get("mask_digest")
        if recorded is not None and digest_file(mask) != recorded:
            raise PromptError(
                f"{self.path}: {where}.mask {mask} is not the file that was recorded (its "
                "content digest differs): restore it, or give the mask with --mask"
            )
        return mask
