"""Any capture with poses and per-view label maps: "a COLMAP or LLFF folder plus masks".

One scene per folder (or the root itself when it holds cameras):

    <scene>/
      <image_dir>/           images (optional: only their size is read; the segmenter sees renders)
      poses_bounds.npy | transforms.json | sparse/0/   the cameras
      <mask_dir>/            one label map per view, matched to views by file name
      gaussians/point_cloud.ply [+ cameras.json]       the trained scene

Label maps are read by `label_format`, one of `sagonline.datasets.labels.LABEL_FORMATS`.

The trajectory is every camera in pseudo-temporal (name) order; the scored views are those with a
label map (optionally without the reference view). The prompt: seeded random clicks on the
reference view's ground truth with its mask beside them (`prompt: mask`; a segmenter reads
either), the clicks alone (`clicks`), the classes as text (`text`) or nothing (`none`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sagonline.core.errors import SceneFileError
from sagonline.datasets.base import DatasetAdapter, DatasetError, EvalView, SceneTask
from sagonline.datasets.common import (
    check_mask_size,
    check_one_mask_size,
    click_prompt,
    list_masks,
    match_by_name,
    scene_cameras,
)
from sagonline.datasets.configs import PosedMasksConfig
from sagonline.datasets.fits import (
    check_photographs_of_the_fit,
    find_trained_scene,
    fit_record,
    gaussians_dir,
    load_trained_scene,
    photographs_fitted,
)
from sagonline.datasets.labels import label_reader
from sagonline.scene.cameras import Camera
from sagonline.scene.io.cameras import CameraFileError, read_poses_bounds
from sagonline.scene.io.images import IMAGE_SUFFIXES, resize_nearest
from sagonline.scene.io.ply import fitted_background
from sagonline.scene.trajectory import nearest_view, shortest_path_order
from sagonline.scene.views import trajectory
from sagonline.segment.prompts import Prompt


class PosedMasksDataset(DatasetAdapter):
    """settings: those of `configs.PosedMasksConfig` (each dataset's config states its own
    defaults)."""

    def __init__(self, root: str | Path, **settings):
        try:
            cfg = PosedMasksConfig(root=str(root), **settings)
        except (TypeError, ValueError) as exc:
            raise DatasetError(f"{settings.get('name', 'generic')}: {exc}") from None
        self.cfg, name = cfg, cfg.name
        self.labels = label_reader(
            cfg.label_format,
            threshold=cfg.mask_threshold,
            names=cfg.label_names,
            ignore=cfg.ignore,
            palette=cfg.palette,
            keep_classes=tuple(cfg.keep_classes),
        )
        self.root, self.name = Path(cfg.root), name
        self.selected = list(cfg.scenes) if cfg.scenes else None
        self.image_dir, self.mask_dir = cfg.image_dir, cfg.mask_dir
        self.label_format, self.threshold = cfg.label_format, cfg.mask_threshold
        self.exclude = tuple(w.lower() for w in cfg.exclude)
        self.ignore = cfg.ignore
        self.prompt_kind, self.clicks, self.reference = cfg.prompt, cfg.clicks, cfg.reference
        self.exclude_reference, self.seed = cfg.exclude_reference, cfg.seed
        self.expected_counts = cfg.expected_counts or {}
        self.expected_photos = cfg.expected_photos
        self.fit = cfg.fit
        self.readme = cfg.readme or f"datasets/{name}/README.md"
        self.render_max_side = cfg.render_max_side
        self.order, self.inbetween = cfg.order, int(cfg.inbetween)
        self.every = int(cfg.every)
        self.drop_nonfinite = cfg.drop_nonfinite

    # --- discovery ----------------------------------------------------------------------------
    def _missing_root(self) -> DatasetError:
        if self.root.is_file():
            return DatasetError(
                f"{self.name}: dataset.root={self.root} is a file; it names the folder that "
                f"holds the scenes (layout: {self.readme})"
            )
        return DatasetError(
            f"{self.name}: no data at {self.root.resolve()}\n"
            f"  Put the dataset there (or pass dataset.root=/path/to/{self.name}).\n"
            f"  Expected per scene: <scene>/{self.image_dir or '<images>'}/, cameras "
            f"(poses_bounds.npy, transforms.json or sparse/0), <scene>/{self.mask_dir}/, and the "
            f"trained scene <scene>/gaussians/point_cloud.ply.\n"
            f"  Layout, licence and download: {self.readme}"
        )

    def _has_cameras(self, d: Path) -> bool:
        return any(
            (d / n).exists()
            for n in (
                "poses_bounds.npy",
                "transforms.json",
                "transforms_train.json",
                "sparse",
                "gaussians/cameras.json",
            )
        )

    def scene_dirs(self) -> dict[str, Path]:
        if not self.root.is_dir():
            raise self._missing_root()
        if self._has_cameras(self.root):
            found = {self.root.name: self.root}
        else:
            found = {
                d.name: d
                for d in sorted(self.root.iterdir())
                if d.is_dir() and self._has_cameras(d)
            }
        if self.selected is not None:
            missing = [s for s in self.selected if s not in found]
            for s in missing:
                found[s] = self.root / s  # reported when loaded, so other scenes still run
            found = {s: found[s] for s in self.selected}
        if not found:
            raise self._missing_root()
        return found

    def scene_names(self) -> list[str]:
        return list(self.scene_dirs())

    @property
    def protocol(self) -> str:
        """What is scored and what the segmenter is offered, e.g. `mold_cape/exclude-reference@2`
        (the default: the reference view's mask with 3 clicks in it, on the first view with a
        mask), `...-clicks1@2` (one click, no mask), `...-mask-clicks1@2`, `...-ref-IMG_5961@2`
        (another reference view); `...-photos1of2@2` where the fits were made from every second
        training photograph (`fit.train_every=2`, the sparse-photograph protocol)."""
        views = "exclude-reference" if self.exclude_reference else "all-views"
        prompt = "" if self.prompt_kind == "mask" else f"-{self.prompt_kind}"
        if self.prompt_kind == "clicks":
            prompt += str(self.clicks)
        elif self.prompt_kind == "mask" and self.clicks != 3:
            prompt += f"-clicks{self.clicks}"
        ref = f"-ref-{self.reference}" if self.reference else ""
        every = {photographs_fitted(d, self.name, self.fit) for d in self._fitted_dirs()}
        sparse = f"-photos1of{max(every)}" if max(every, default=1) > 1 else ""
        return f"{self.name}/{views}{prompt}{ref}{sparse}@{self.protocol_version}"

    def _fitted_dirs(self) -> list[Path]:
        """The scenes' folders, where they can be listed (none: the protocol names no fit)."""
        try:
            return list(self.scene_dirs().values())
        except DatasetError:
            return []

    def check_segmenter(self, reads: tuple[str, ...]) -> None:
        """Refuse a protocol that says something other than what the segmenter will receive:
        the clicks' count under the mask protocol, for a segmenter that reads the mask (it never
        sees the clicks)."""
        if self.prompt_kind == "mask" and self.clicks != 3 and "masks" in reads:
            raise DatasetError(
                f"{self.name}: dataset.adapter.clicks={self.clicks} changes nothing for this "
                "segmenter: it reads the reference mask (segmenter.use_masks=true), not the "
                "clicks. For a click protocol set dataset.adapter.prompt=clicks (or "
                "segmenter.use_masks=false)"
            )

    def describe(self) -> dict:
        return {
            "protocol_id": self.protocol,
            "label_format": self.label_format,
            "prompt": self.prompt_kind,
            "clicks": self.clicks,
            "exclude_reference": self.exclude_reference,
            "excluded_mask_words": list(self.exclude),
            "mask_threshold": self.threshold,
            "pseudo_temporal_order": (
                "camera names sorted lexicographically"
                if self.order == "name"
                else "shortest path through the camera poses from the reference view"
            ),
        }

    # --- views --------------------------------------------------------------------------------
    def image_dir_for(self, scene: str) -> str | None:
        return self.image_dir

    def load_views(self, scene: str) -> tuple[list[Camera], dict[str, Path]]:
        """Cameras (sorted) and the label-map path of every view that has one."""
        scene_dir = self.scene_dirs()[scene]
        if not scene_dir.is_dir():
            raise DatasetError(f"{self.name}: scene folder {scene_dir} not found")
        mask_root = scene_dir / self.mask_dir
        if self.label_format == "per_object":
            if not mask_root.is_dir():
                raise DatasetError(f"mask folder {mask_root} not found")
            entries = sorted(p for p in mask_root.iterdir() if p.is_dir())
        else:
            entries = list_masks(mask_root, self.exclude)
        if not entries:
            raise DatasetError(f"{mask_root}: no label maps found")
        names = None
        pb = scene_dir / "poses_bounds.npy"
        gs_dir = gaussians_dir(scene_dir, self.name, self.fit)
        if pb.is_file() and not (gs_dir / "cameras.json").is_file():
            try:
                n_poses = len(read_poses_bounds(pb))
            except CameraFileError as exc:
                raise DatasetError(str(exc)) from None
            image_folder = scene_dir / (self.image_dir_for(scene) or "images")
            images = (
                sorted(p.stem for p in image_folder.iterdir() if p.suffix in IMAGE_SUFFIXES)
                if image_folder.is_dir()
                else []
            )
            mask_names = sorted({e.stem.removesuffix("_mask") for e in entries})
            # LLFF rows follow the sorted full image list; a capture that ships only some
            # images (or masks for all) names the views by whichever list is complete.
            names = next((n for n in (images, mask_names) if len(n) == n_poses), None)
            if names is None:
                raise DatasetError(
                    f"{pb}: {n_poses} poses, but {image_folder} has {len(images)} images and "
                    f"{mask_root} {len(mask_names)} label maps; cannot tell which pose is whose"
                )
        cams = scene_cameras(scene_dir, self.image_dir_for(scene), names, self.name, self.fit)
        masks = match_by_name(entries, [c.name for c in cams], scene_dir)
        expected = self.expected_counts.get(scene)
        if expected is not None and len(masks) != expected:
            raise DatasetError(
                f"{mask_root}: {len(masks)} label maps, the protocol expects "
                f"{expected} (cutout/pseudo files excluded)"
            )
        return cams, masks

    def photographed(self, scene: str, scene_dir: Path, cams: list[Camera]) -> list[str]:
        """Names of the views with a photograph in the scene's image folder (what a fit sees;
        the other views have poses and masks only). A missing folder, or fewer photographs
        than the protocol expects (`expected_photos`), is refused: the view groups would
        change without a word."""
        folder = scene_dir / (self.image_dir_for(scene) or "images")
        if not folder.is_dir():
            if self.expected_photos:
                raise DatasetError(
                    f"{self.name}/{scene}: image folder {folder} not found; the protocol "
                    f"expects {self.expected_photos} photographs there (they define its "
                    "photographed and mask-only view groups)"
                )
            return []
        names = {c.name for c in cams}
        found = sorted(
            p.stem for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES and p.stem in names
        )
        if self.expected_photos is not None and len(found) != self.expected_photos:
            raise DatasetError(
                f"{folder}: {len(found)} photographs of the scene's views, the protocol expects "
                f"{self.expected_photos} (a missing or extra one would move views between the "
                "photographed and mask-only groups)"
            )
        return found

    def capture(self, scene: str) -> tuple[Path, list[Camera], dict[str, Path]]:
        """What `make scenes` fits from: the scene folder, every camera, and the images found
        (by view name) in the scene's image folder."""
        cams, _ = self.load_views(scene)
        scene_dir = self.scene_dirs()[scene]
        folder = scene_dir / (self.image_dir_for(scene) or "images")
        if not folder.is_dir():
            raise DatasetError(f"{self.name}/{scene}: image folder {folder} not found")
        names = {c.name for c in cams}
        images = {
            p.stem: p
            for p in sorted(folder.iterdir())
            if p.suffix in IMAGE_SUFFIXES and p.stem in names
        }
        return scene_dir, cams, images

    def read_label_map(self, path: Path) -> np.ndarray:
        """One view's (H, W) label map of integer ids (per_object: a folder of masks)."""
        return self.labels.read(path)

    # --- task ---------------------------------------------------------------------------------
    def load_scene(self, scene: str) -> SceneTask:
        cams, mask_paths = self.load_views(scene)
        if self.render_max_side:  # render smaller; scores still use the masks' resolution
            cams = [c.scaled(*_fit_within(c.width, c.height, self.render_max_side)) for c in cams]
        scene_dir = self.scene_dirs()[scene]
        by_name = {c.name: c for c in cams}
        gts = {}
        for name, path in mask_paths.items():
            gt = self.read_label_map(path)
            check_mask_size(gt, by_name[name], path)
            gts[name] = gt
        check_one_mask_size(gts, mask_paths)
        gts, names = self.labels.finish(gts, scene_dir / self.mask_dir)
        num_labels = len(names)
        gaussians = load_trained_scene(scene_dir, self.name, self.drop_nonfinite, self.fit)
        scene_file = find_trained_scene(scene_dir, self.name, self.fit)
        try:
            background = fitted_background(scene_file)
        except SceneFileError as exc:
            raise DatasetError(str(exc)) from exc
        for name, gt in gts.items():
            valid = gt if self.ignore is None else gt[gt != self.ignore]
            if valid.size and (valid.min() < 0 or valid.max() >= num_labels):
                raise DatasetError(f"{mask_paths[name]}: label ids outside [0, {num_labels})")
        reference = self.reference or sorted(gts)[0]
        if reference not in gts:
            raise DatasetError(f"{self.name}/{scene}: reference view {reference!r} has no mask")
        if self.order == "path":  # the video starts at the prompt and moves as little as it can
            start = [c.name for c in cams].index(reference)
            cams = [cams[i] for i in shortest_path_order(cams, start)]
        views = cams  # every view: the photographed ones are found among them
        keep = [c.name for c in cams].index(reference)
        cams = trajectory(cams, every=self.every, keep=keep, inbetween=self.inbetween)
        frame = [c.name for c in cams].index(reference)
        prompt = self.make_prompt(gts[reference], by_name[reference], frame, num_labels, names)
        scored = [n for n in sorted(gts) if not (self.exclude_reference and n == reference)]
        evals = [EvalView(by_name[n], gts[n], n) for n in scored]
        photographs = self.photographed(scene, scene_dir, views)
        check_photographs_of_the_fit(scene_file, scene_dir, photographs, self.expected_photos)
        view_groups = group_by_photographs(evals, views, photographs)
        traj_gt = None
        if all(c.name in gts for c in cams):
            traj_gt = [resize_nearest(gts[c.name], (c.height, c.width)) for c in cams]
            traj_gt = [g.astype(np.int64) for g in traj_gt]  # int64: as the masks stage keys it
        return SceneTask(
            dataset=self.name,
            name=scene,
            gaussians=gaussians,
            trajectory=cams,
            eval_views=evals,
            num_labels=num_labels,
            prompt=prompt,
            trajectory_gt=traj_gt,
            label_names=names,
            meta={
                "reference": reference,
                "scored_views": len(evals),
                "root": str(scene_dir),
                "fit": fit_record(scene_dir, self.name, self.fit),
                "scene_file": str(scene_file),
                "photographs": photographs,
                "order": self.order,
            },
            ignore_label=self.ignore,
            view_groups=view_groups,
            background=background,
        )

    def make_prompt(
        self, gt: np.ndarray, cam: Camera, frame: int, num_labels: int, names: list[str]
    ) -> Prompt:
        if self.prompt_kind == "none":
            return Prompt(frame=frame)
        if self.prompt_kind == "text":
            return Prompt(frame=frame, texts=names[1:])
        scale = (cam.width / gt.shape[1], cam.height / gt.shape[0])
        clean = np.where(gt == self.ignore, 0, gt) if self.ignore is not None else gt
        prompt = click_prompt(clean, frame, num_labels, self.clicks, self.seed, scale)
        if self.prompt_kind == "clicks":  # the clicks alone: no mask is offered
            for obj in prompt.objects:
                obj.mask = None
        return prompt


def group_by_photographs(
    evals: list[EvalView], cams: list[Camera], photographs: list[str]
) -> list[str]:
    """For a capture with photographs (of some views, or all): each eval view's group
    ("photographed" or "mask_only") and, in its metadata, the angle (degrees) and distance to
    the nearest photographed camera. Returns the groups, or [] when nothing was photographed."""
    if not photographs or not evals:
        return []
    photos = set(photographs)
    photo_cams = [c for c in cams if c.name in photos]
    angle, dist = nearest_view([v.camera for v in evals], photo_cams)
    for view, a, d in zip(evals, angle, dist, strict=True):
        shot = view.name in photos
        view.group = "photographed" if shot else "mask_only"
        view.meta.update(
            photographed=shot,
            photo_angle_deg=0.0 if shot else float(a),
            photo_distance=0.0 if shot else float(d),
        )
    return ["photographed", "mask_only"]


def _fit_within(width: int, height: int, max_side: int) -> tuple[int, int]:
    scale = min(1.0, max_side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))
