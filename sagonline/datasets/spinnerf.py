"""SPIn-NeRF multiview segmentation benchmark (10 scenes), scored as in datasets/spinnerf/README.md.

    <root>/<scene>/images_4|images_8/   the capture (LLFF scenes: poses_bounds.npy;
                                        lego: transforms.json or poses_bounds.npy)
    <root>/<scene>/labels/*.png         the released annotations; names with `cutout` or
                                        `pseudo` are not ground truth and are skipped
    <root>/<scene>/gaussians/point_cloud.ply

Masks are matched to images by name (orchids has an image without a mask), the reference
(prompt) view is the first masked view in lexicographic order, and every masked view is scored
unless `exclude_reference`.
"""

from __future__ import annotations

from sagonline.datasets.generic import PosedMasksDataset

# scene: (image folder of its common resolution, expected number of ground-truth masks)
SCENES = {
    "orchids": ("images_4", 24),
    "leaves": ("images_4", 26),
    "fern": ("images_4", 20),
    "room": ("images_8", 41),
    "horns": ("images_4", 62),
    "fortress": ("images_4", 42),
    "fork": ("images_4", 38),
    "pinecone": ("images_8", 99),
    "truck": ("images_4", 65),
    "lego": ("images_4", 44),
}


class SPInNeRFDataset(PosedMasksDataset):
    def __init__(
        self,
        root="datasets/spinnerf",
        scenes=None,
        exclude_reference=False,
        clicks=3,
        seed=0,
        mask_dir="labels",
        check_counts=True,
        **kwargs,
    ):
        super().__init__(
            root,
            name="spinnerf",
            scenes=scenes or list(SCENES),
            image_dir=None,
            mask_dir=mask_dir,
            label_format="binary",
            exclude=("cutout", "pseudo"),
            prompt="clicks",
            clicks=clicks,
            exclude_reference=exclude_reference,
            seed=seed,
            expected_counts={s: n for s, (_, n) in SCENES.items()} if check_counts else None,
            **kwargs,
        )

    def image_dir_for(self, scene: str) -> str | None:
        return SCENES.get(scene, ("images_4", None))[0]

    def scene_dirs(self):
        dirs = {s: self.root / s for s in self.selected}
        if not any(d.is_dir() for d in dirs.values()):  # datasets/spinnerf holds only its README
            raise self._missing_root()
        return dirs

    def describe(self) -> dict:
        return {
            **super().describe(),
            "resolutions": {s: d for s, (d, _) in SCENES.items()},
            "reference": "first masked view after a lexicographic sort",
            "scored": "all masked views"
            + (" except the reference" if self.exclude_reference else ""),
        }
