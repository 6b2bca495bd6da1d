"""NVOS: 8 single-view segmentation tasks on LLFF scenes, scored as in datasets/nvos/README.md.

Two layouts are read. The released one (annotations under `labels/llff/`, scenes as COLMAP
`<scene>_undistort/` folders):

    <root>/labels/llff/masks/<task>/<target>_mask.png        ground truth of the target view
    <root>/labels/llff/reference_image/<task>/<reference>.JPG
    <root>/labels/llff/scribbles/<task>/pos_0_<scene>.png, neg_0_<scene>.png
    <root>/scenes/<scene>_undistort/  images/, sparse/0/ (COLMAP), gaussians/point_cloud.ply

and the flat one (everything at the root, LLFF scenes):

    <root>/masks/<task>/..., <root>/reference_image/<task>/..., <root>/scribbles/<task>/...
    <root>/scenes/<scene>/    images_4/, poses_bounds.npy, gaussians/point_cloud.ply

`scenes_root` points at captures kept elsewhere; a scene folder is `<scene>` or
`<scene>_undistort`, with LLFF or COLMAP cameras. Scribbles are `pos_*` / `neg_*` of any
numbering, at any resolution (the release's are 4x downsampled): each is scaled from its own
size to the view's. Without `image_dir` images to size the cameras by, they are scaled to the
ground-truth mask's resolution.

Each task prompts on its reference view by one of the protocols of `nvos_prompts` (scribbles
sampled uniformly or SAGA's skeleton way, one click, a frozen points file), or, as the SAGOnline
paper does, by seeded random clicks on the ground-truth object, which NVOS only provides on the
target view; it scores the single target view. `protocol` names the choice (e.g.
`nvos/scribbles-skeleton@2`) and every result carries it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from sagonline.datasets.base import DatasetAdapter, DatasetError, EvalView, SceneTask
from sagonline.datasets.common import check_mask_size, click_prompt, load_mask, scene_cameras
from sagonline.datasets.fits import find_trained_scene, fit_record, load_trained_scene
from sagonline.datasets.nvos_prompts import (
    check_inside,
    read_points_file,
    skeleton_points,
    uniform_points,
)
from sagonline.segment.prompts import ObjectPrompt, Prompt

PROMPTS = ("scribbles", "click", "points", "clicks")
TASKS = {
    "fern": ("IMG_4027", "IMG_4038"),
    "flower": ("IMG_2962", "IMG_2983"),
    "fortress": ("IMG_1800", "IMG_1821"),
    "horns_center": ("DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "horns_left": ("DJI_20200223_163024_597", "DJI_20200223_163055_437"),
    "leaves": ("IMG_2997", "IMG_3011"),
    "orchids": ("IMG_4480", "IMG_4479"),
    "trex": ("DJI_20200223_163619_411", "DJI_20200223_163607_906"),
}


class NVOSDataset(DatasetAdapter):
    name = "nvos"

    def __init__(
        self,
        root="datasets/nvos",
        tasks=None,
        image_dir="images_4",
        prompt="scribbles",
        sampling="uniform",
        points_file=None,
        clicks=3,
        scribble_points=16,
        negative=False,
        seed=0,
        mask_threshold=127,
        scenes_root=None,
        drop_nonfinite=False,
    ):
        if prompt not in PROMPTS:
            raise DatasetError(f"nvos: prompt {prompt!r} is not one of {PROMPTS}")
        if sampling not in ("uniform", "skeleton"):
            raise DatasetError(f"nvos: sampling {sampling!r} is not 'uniform' or 'skeleton'")
        if (prompt == "points") != (points_file is not None):
            raise DatasetError(
                "nvos: prompt=points reads dataset.adapter.points_file, which is only for it"
            )
        self.root, self.image_dir, self.prompt_kind = Path(root), image_dir, prompt
        self.sampling = sampling
        self.tasks = list(tasks) if tasks else list(TASKS)
        unknown = [t for t in self.tasks if t not in TASKS]
        if unknown:
            raise DatasetError(f"nvos: unknown task(s) {unknown}; tasks are {list(TASKS)}")
        self.points_file, self.frozen, self.points_scale = points_file, {}, 1.0
        if points_file is not None:
            self.frozen, self.points_scale = read_points_file(points_file, self.tasks, list(TASKS))
        self.clicks, self.points, self.negative = clicks, scribble_points, negative
        self.seed, self.threshold = seed, mask_threshold
        self.drop_nonfinite = drop_nonfinite
        self.scenes_root = Path(scenes_root) if scenes_root else self.root / "scenes"

    @property
    def labels(self) -> Path:
        """Where the annotations are: `labels/llff/` (the release) or the root itself."""
        released = self.root / "labels" / "llff"
        return released if released.is_dir() else self.root

    def scene_dir(self, task: str) -> Path:
        scene = self.scene_of(task)
        for name in (scene, f"{scene}_undistort"):
            if (self.scenes_root / name).is_dir():
                return self.scenes_root / name
        raise DatasetError(
            f"nvos/{task}: scene folder {self.scenes_root / scene} (or {scene}_undistort) not found"
        )

    def scene_names(self) -> list[str]:
        if not (self.labels / "masks").is_dir() or not self.scenes_root.is_dir():
            raise DatasetError(
                f"nvos: no data at {self.root.resolve()} (scenes: {self.scenes_root})\n"
                "  Expected the released layout:\n"
                "    labels/llff/masks/<task>/<target>_mask.png\n"
                "    labels/llff/reference_image/<task>/\n"
                "    labels/llff/scribbles/<task>/pos_0_<scene>.png (neg_0_... optional)\n"
                "    scenes/<scene>_undistort/ (COLMAP: images/, sparse/0/) + "
                "gaussians/point_cloud.ply\n"
                "  or the flat one: masks/<task>/, reference_image/<task>/, scribbles/<task>/,\n"
                "    scenes/<scene>/ (LLFF: images_4/, poses_bounds.npy) + "
                "gaussians/point_cloud.ply\n"
                "  Put the dataset there or pass dataset.root=/path/to/nvos (and "
                "dataset.adapter.scenes_root=... for captures kept elsewhere). Layout, licence "
                "and download: datasets/nvos/README.md"
            )
        return self.tasks

    @property
    def protocol(self) -> str:
        """The versioned id of this prompt protocol (every result carries it)."""
        neg = "-neg" if self.negative else ""
        if self.prompt_kind == "points":
            digest = hashlib.sha256(Path(self.points_file).read_bytes()).hexdigest()[:8]
            return f"nvos/points-{Path(self.points_file).stem}-{digest}@{self.protocol_version}"
        if self.prompt_kind == "click":
            return f"nvos/click@{self.protocol_version}"
        if self.prompt_kind == "clicks":
            return f"nvos/gt-clicks{self.clicks}@{self.protocol_version}"
        if self.sampling == "skeleton":
            return f"nvos/scribbles-skeleton{neg}@{self.protocol_version}"
        return f"nvos/scribbles-uniform{self.points}{neg}@{self.protocol_version}"

    def describe(self) -> dict:
        return {
            "tasks": {t: {"target": a, "reference": b} for t, (a, b) in TASKS.items()},
            "protocol_id": self.protocol,
            "prompt": self.prompt_kind,
            "scored": "the target view of each task",
            "pseudo_temporal_order": "image names sorted lexicographically",
        }

    @staticmethod
    def scene_of(task: str) -> str:
        return task.split("_")[0]

    def load_scene(self, task: str) -> SceneTask:
        target, reference = TASKS[task]
        scene_dir = self.scene_dir(task)
        cams = scene_cameras(scene_dir, self.image_dir, dataset="nvos")
        names = [c.name for c in cams]
        for role, view in (("target", target), ("reference", reference)):
            if view not in names:
                raise DatasetError(
                    f"nvos/{task}: {role} view {view} is not among the "
                    f"{len(names)} views of {scene_dir} ({self.image_dir})"
                )
        mask_path = self.labels / "masks" / task / f"{target}_mask.png"
        if not mask_path.is_file():
            raise DatasetError(f"nvos/{task}: ground truth {mask_path} not found")
        gt = load_mask(mask_path, self.threshold)
        target_cam = cams[names.index(target)]
        check_mask_size(gt, target_cam, mask_path)
        if not (scene_dir / self.image_dir).is_dir():  # e.g. COLMAP at full size: render at GT's
            sx, sy = gt.shape[1] / target_cam.width, gt.shape[0] / target_cam.height
            cams = [c.scaled(round(c.width * sx), round(c.height * sy)) for c in cams]
            target_cam = cams[names.index(target)]
        gaussians = load_trained_scene(scene_dir, "nvos", self.drop_nonfinite)
        if self.prompt_kind == "clicks":
            frame = names.index(target)
            scale = (target_cam.width / gt.shape[1], target_cam.height / gt.shape[0])
            prompt = click_prompt(gt, frame, 2, self.clicks, self.seed, scale)
        else:
            frame = names.index(reference)
            if self.prompt_kind == "points":
                obj = self.frozen_prompt(task, cams[frame], gt.shape)
            else:
                obj = self.scribble_prompt(task, cams[frame])
            prompt = Prompt(frame=frame, objects=[obj])
        return SceneTask(
            dataset="nvos",
            name=task,
            gaussians=gaussians,
            trajectory=cams,
            eval_views=[EvalView(target_cam, gt, target)],
            num_labels=2,
            prompt=prompt,
            label_names=["background", task],
            meta={
                "target": target,
                "reference": reference,
                "prompt": self.prompt_kind,
                "protocol": self.protocol,
                "fit": fit_record(scene_dir, "nvos"),
                "scene_file": str(find_trained_scene(scene_dir, "nvos")),
            },
        )

    def capture(self, scene: str) -> tuple[Path, list, dict[str, Path]]:
        """The LLFF scene behind a task (or a scene name): folder, cameras, images."""
        from sagonline.scene.io.images import list_images

        scene_dir = self.scene_dir(scene)
        cams = scene_cameras(scene_dir, self.image_dir)
        folder = scene_dir / self.image_dir
        images = {
            p.stem: p for p in list_images(folder if folder.is_dir() else scene_dir / "images")
        }
        return scene_dir, cams, images

    def scribble_prompt(self, task: str, cam) -> ObjectPrompt:
        """Points from the reference view's scribbles: uniform or skeleton sampling (seeded), or
        one positive pixel (prompt=click)."""
        folder = self.labels / "scribbles" / task
        rng = np.random.default_rng(self.seed)
        pts, labels = [], []
        for kind, value in (("pos", 1), ("neg", 0)):
            if kind == "neg" and (not self.negative or self.prompt_kind == "click"):
                continue
            files = sorted(folder.glob(f"{kind}_*.png"))
            if kind == "pos" and not files:
                raise DatasetError(f"nvos/{task}: no positive scribbles {folder}/pos_*.png")
            for f in files:
                m = load_mask(f, self.threshold)
                if not m.any():
                    continue
                if self.prompt_kind == "click":
                    xy = uniform_points(m, rng, 1)
                elif self.sampling == "skeleton":
                    xy = skeleton_points(m, rng, positive=value == 1)
                else:
                    xy = uniform_points(m, rng, self.points)
                sx, sy = cam.width / m.shape[1], cam.height / m.shape[0]
                pts.append(np.stack([(xy[:, 0] + 0.5) * sx, (xy[:, 1] + 0.5) * sy], 1))
                labels.append(np.full(len(xy), value))
                if self.prompt_kind == "click":
                    break
        if not pts:
            raise DatasetError(f"nvos/{task}: the scribbles in {folder} are empty")
        return ObjectPrompt(
            label=1,
            points=np.concatenate(pts),
            point_labels=np.concatenate(labels).astype(np.int64),
        )

    def frozen_prompt(self, task: str, cam, mask_shape: tuple[int, int]) -> ObjectPrompt:
        """The points file's clicks for `task`, from the original resolution (the released
        masks' size times `_scale`) to the reference view's pixels."""
        pts = self.frozen[task]
        width, height = mask_shape[1] * self.points_scale, mask_shape[0] * self.points_scale
        check_inside(pts, round(width), round(height), f"nvos: {self.points_file}, task {task!r}")
        xy = pts * np.array([cam.width / width, cam.height / height])
        return ObjectPrompt(label=1, points=xy, point_labels=np.ones(len(xy), dtype=np.int64))
