"""One small typed config per dataset, each setting stated once, on its field; each is
registered under its key in `plugins.DATASETS` with the adapter it builds (`registry.py`). The
entry points turn every registered dataset into a Hydra config (`dataset=<key>`, root
`datasets/<key>`), so a dataset needs no YAML; a YAML in conf/dataset/ only says where another
copy of a dataset's data is (`defaults: [<key>]` and `root:`).

The captures with poses and per-view label maps share one adapter (`generic.PosedMasksDataset`)
whose settings differ per dataset only in their defaults: each dataset's config below states
those. NVOS, SPIn-NeRF and the synthetic scenes have adapters of their own.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from sagonline.core.settings import check_settings
from sagonline.datasets.fits import is_variant_name
from sagonline.datasets.labels import KITTI360_VEHICLES, LABEL_FORMATS

PROMPTS = ("mask", "clicks", "text", "none")
ORDERS = ("name", "path")


@dataclass
class PosedMasksConfig:
    """Any capture with poses and per-view label maps (`dataset=generic`)."""

    root: str = "datasets/generic"
    """One scene per folder below it, or the scene folder itself."""
    name: str = "generic"
    """The dataset's name in reports, and in `scenes/<name>/` for fits of read-only data."""
    scenes: list[str] | None = None
    """The scenes to run (folder names); None: every folder with cameras."""
    image_dir: str | None = "images_4"
    """Image folder of a scene: only the images' size is read (the segmenter sees renders)."""
    mask_dir: str = "masks"
    """Label-map folder of a scene: one map per view, matched to the views by file name."""
    label_format: str = "binary"
    """How label maps read: binary | ids | palette | per_object | kitti360 (datasets.labels)."""
    mask_threshold: int = 127
    """binary / per_object: foreground where a channel exceeds this (0 for 0/1 masks)."""
    exclude: list[str] = field(default_factory=lambda: ["cutout", "pseudo"])
    """Mask files whose names hold one of these words are not ground truth."""
    palette: dict[str, int] | None = None
    """palette: "r,g,b" -> label id."""
    label_names: list[str] | None = None
    """ids / palette: the label names, background first; None: "1", "2", ..."""
    ignore: int | None = None
    """A ground-truth value never scored (void pixels)."""
    prompt: str = "mask"
    """mask (the reference view's ground-truth mask, with `clicks` seeded clicks in it: a
    segmenter reads either) | clicks (the clicks alone) | text (the label names) | none."""
    clicks: int = 3
    """Positive clicks per object."""
    reference: str | None = None
    """The prompt view; None: the first view with a label map."""
    exclude_reference: bool = False
    """Leave the prompt view out of the scored views."""
    expected_counts: dict[str, int] | None = None
    """Label maps a scene must have (the protocol's counts); None: not checked."""
    fit: str = ""
    """Which fit of each scene to evaluate: '' the default (gaussians/), or a variant
    (gaussians-<fit>/: `seed1`, `seed2`, ..., as `make scenes ARGS=seed=1` writes them)."""
    expected_photos: int | None = None
    """Photographs each scene's image folder must hold (its views' photographed / mask-only
    groups depend on them: a missing photograph would move a view between them); None: not
    checked."""
    readme: str | None = None
    """Where the layout is explained; None: datasets/<name>/README.md."""
    keep_classes: list[int] = field(default_factory=lambda: list(KITTI360_VEHICLES))
    """kitti360: the Cityscapes classes whose instances are kept (vehicles)."""
    render_max_side: int | None = None
    """Render at most this many pixels on the longer side (scores stay at the masks' size)."""
    order: str = "name"
    """Video order: name (the NVOS/SPIn-NeRF protocol) | path (shortest path through the poses
    from the reference view)."""
    every: int = 1
    """Render and segment every `every`-th view of the video only (and the reference view): a
    segmenter's time over `every`, a sparser video for it; every view is still scored."""
    inbetween: int = 0
    """Cameras slerped between consecutive views (rendered for the segmenter only)."""
    seed: int = 0
    """Seeds the clicks."""
    drop_nonfinite: bool = False
    """Drop Gaussians with NaN/Inf (or overflowing) values, with a warning, instead of failing."""

    def __post_init__(self) -> None:
        check_settings(
            "dataset.adapter",
            label_format=(
                self.label_format in LABEL_FORMATS,
                self.label_format,
                f"one of {LABEL_FORMATS}",
            ),
            prompt=(self.prompt in PROMPTS, self.prompt, f"one of {PROMPTS}"),
            order=(self.order in ORDERS, self.order, f"one of {ORDERS}"),
            clicks=(self.clicks >= 1, self.clicks, ">= 1"),
            fit=(
                not self.fit or is_variant_name(self.fit),
                self.fit,
                "a fit variant's plain name (letters, digits, - _ .), never a path",
            ),
            every=(self.every >= 1, self.every, ">= 1"),
            inbetween=(self.inbetween >= 0, self.inbetween, ">= 0"),
            mask_threshold=(0 <= self.mask_threshold < 256, self.mask_threshold, "in [0, 256)"),
        )


@dataclass
class KITTI360Config(PosedMasksConfig):
    """KITTI-360 vehicle instances, segmented automatically (YOLO + tracker)."""

    name: str = "kitti360"
    image_dir: str | None = "image_00"
    mask_dir: str = "instance"
    label_format: str = "kitti360"
    prompt: str = "none"


@dataclass
class UDDConfig(PosedMasksConfig):
    """UDD6 drone semantics, open-vocabulary text prompts (SAM 3)."""

    name: str = "udd"
    image_dir: str | None = "src"
    mask_dir: str = "gt"
    label_format: str = "palette"
    palette: dict[str, int] | None = field(
        default_factory=lambda: {
            "0,0,0": 0,
            "102,102,156": 1,
            "128,64,128": 2,
            "107,142,35": 3,
            "0,0,142": 4,
            "70,70,70": 5,
        }
    )
    label_names: list[str] | None = field(
        default_factory=lambda: ["other", "facade", "road", "vegetation", "vehicle", "roof"]
    )
    prompt: str = "text"


@dataclass
class Mip360Config(PosedMasksConfig):
    """Mip-NeRF 360 with per-view instance-id masks, click prompts."""

    name: str = "mip360"
    mask_dir: str = "instance_masks"
    label_format: str = "ids"


@dataclass
class LERFMaskConfig(PosedMasksConfig):
    """LERF-Mask (Gaussian Grouping's release): per-object test masks, text queries."""

    name: str = "lerf_mask"
    image_dir: str | None = "images"
    mask_dir: str = "test_mask"
    label_format: str = "per_object"
    prompt: str = "text"


@dataclass
class Desktop360Config(PosedMasksConfig):
    """DesktopObjects-360: tabletop 360-degree captures with instance masks."""

    name: str = "desktop360"
    image_dir: str | None = "images"
    mask_dir: str = "instance_masks"
    label_format: str = "ids"


@dataclass
class NeRDS360Config(PosedMasksConfig):
    """NeRDS-360: outdoor multi-object scenes with instance masks (255: void)."""

    name: str = "nerds360"
    image_dir: str | None = "rgb"
    mask_dir: str = "instance"
    label_format: str = "ids"
    ignore: int | None = 255


@dataclass
class CaptureConfig(PosedMasksConfig):
    """A real 360-degree capture in one layout (`dataset=capture dataset.root=PATH`): images_4/
    (the photographs a fit sees), masks_4/ (a binary object mask per view, the ground truth),
    poses_bounds.npy (LLFF, one row per mask). The four shared captures are
    this layout; a capture of one's own is a dataset by configuration alone."""

    name: str = "capture"
    root: str = "datasets/capture"
    mask_dir: str = "masks_4"
    render_max_side: int | None = 228
    """Render at the fitted scene's resolution (`fit.max_side`); the masks are scored at theirs."""


@dataclass
class SPInNeRFConfig:
    """SPIn-NeRF: 10 scenes, every masked view scored."""

    root: str = "datasets/spinnerf"
    """The folder holding the scenes."""
    scenes: list[str] | None = None
    """None: all 10."""
    exclude_reference: bool = False
    """Leave the reference (prompt) view out of the scored views (disputed; off by default)."""
    clicks: int = 3
    """Positive clicks on the reference view's object."""
    seed: int = 0
    drop_nonfinite: bool = False
    """Drop Gaussians with NaN/Inf (or overflowing) values, with a warning, instead of failing."""


@dataclass
class NVOSConfig:
    """NVOS: 8 tasks, the target view of each scored."""

    root: str = "datasets/nvos"
    """The release's folder (labels/llff/... and the scenes)."""
    tasks: list[str] | None = None
    """None: all 8."""
    image_dir: str = "images_4"
    prompt: str = "scribbles"
    """scribbles (the reference view's, sampled) | click (one positive scribble pixel) | points
    (a frozen points file) | clicks (seeded, on the target view's ground truth, as the SAGOnline
    paper does)."""
    sampling: str = "uniform"
    """prompt=scribbles: uniform (scribble_points per scribble) | skeleton (SAGA's)."""
    points_file: str | None = None
    """prompt=points: JSON {task: [[x, y], ...], "_scale": 4} at the original resolution."""
    clicks: int = 3
    scribble_points: int = 16
    """Points sampled from each scribble with sampling=uniform."""
    negative: bool = False
    """Also sample the negative scribbles."""
    seed: int = 0
    mask_threshold: int = 127
    scenes_root: str | None = None
    """Captures kept elsewhere: <scenes_root>/<scene> or <scene>_undistort."""
    drop_nonfinite: bool = False
    """Drop Gaussians with NaN/Inf (or overflowing) values, with a warning, instead of failing."""


SYNTHETIC_LAYOUTS = ("forward", "360")
SYNTHETIC_TASKS = ("instance", "semantic")
MAX_SYNTHETIC_VIEWS = 2000
MAX_SYNTHETIC_GAUSSIANS = 5_000_000


@dataclass
class SyntheticPreset:
    """One generated scene (`sagonline.scene.generator.make_scene`)."""

    layout: str = "360"
    """forward: one object, cameras on a 60-degree arc (NVOS-like); 360: objects clustered
    on a table, cameras on a full orbit (DesktopObjects-like)."""
    task: str = "instance"
    """instance: objects labelled 1..K; semantic: shapes labelled by class."""
    num_objects: int = 5
    """Objects in a 360 scene (a forward scene has one)."""
    num_gaussians: int = 20000
    width: int = 320
    height: int = 240
    num_train_views: int = 36
    """Trajectory views (the segmenter's video)."""
    num_eval_views: int = 8
    """Held-out views between the trajectory views, where the labels are scored."""
    clicks: int = 3
    """Positive clicks per object on the first view's ground truth."""
    seed: int = 0

    def check(self, where: str) -> None:
        """Each setting in its range (a mistyped size or count stops, naming its key)."""
        views, n = MAX_SYNTHETIC_VIEWS, MAX_SYNTHETIC_GAUSSIANS
        check_settings(
            where,
            layout=(self.layout in SYNTHETIC_LAYOUTS, self.layout, f"one of {SYNTHETIC_LAYOUTS}"),
            task=(self.task in SYNTHETIC_TASKS, self.task, f"one of {SYNTHETIC_TASKS}"),
            num_objects=(1 <= self.num_objects <= 9, self.num_objects, "in [1, 9]"),
            num_gaussians=(100 <= self.num_gaussians <= n, self.num_gaussians, f"in [100, {n}]"),
            width=(16 <= self.width <= 4096, self.width, "in [16, 4096] pixels"),
            height=(16 <= self.height <= 4096, self.height, "in [16, 4096] pixels"),
            num_train_views=(
                2 <= self.num_train_views <= views,
                self.num_train_views,
                f"in [2, {views}]",
            ),
            num_eval_views=(
                1 <= self.num_eval_views <= views,
                self.num_eval_views,
                f"in [1, {views}]",
            ),
            clicks=(1 <= self.clicks <= 100, self.clicks, "in [1, 100]"),
        )


@dataclass
class SyntheticConfig:
    """The embedded default: generated 2DGS scenes with per-Gaussian ground truth."""

    name: str = "synthetic"
    root: str = ""
    """Unused: the scenes are generated."""
    forward_single: SyntheticPreset = field(
        default_factory=lambda: SyntheticPreset(layout="forward", num_objects=1)
    )
    """A forward-facing single object (NVOS-like)."""
    cluttered_360: SyntheticPreset = field(default_factory=SyntheticPreset)
    """A cluttered 360-degree multi-object scene (DesktopObjects-like)."""
    scenes: list[str] | None = None
    """The presets to run (forward_single, cluttered_360); None: both."""
    device: str = "cpu"
    """Where the ground truth is rendered: the run's device (a GPU run renders it there, with
    the label walk the vote uses, instead of building and running the CPU kernel first)."""

    def __post_init__(self) -> None:
        for name, preset in self.presets().items():
            preset.check(f"dataset.adapter.{name}")
        unknown = sorted(set(self.scenes or []) - set(self.presets()))
        check_settings(
            "dataset.adapter",
            scenes=(not unknown, self.scenes, f"a list of {sorted(self.presets())}"),
        )

    def presets(self) -> dict[str, SyntheticPreset]:
        return {"forward_single": self.forward_single, "cluttered_360": self.cluttered_360}
