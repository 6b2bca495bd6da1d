"""Where a scene's fit lives, read and written: its folder (`gaussians/`, `gaussians-<variant>/`,
or the project's overlay for data on a read-only disk), its point_cloud.ply and what `make scenes`
recorded beside it, whether a file there is a fit of ours, and a finished fit copied as another
recipe's."""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from pathlib import Path

from sagonline.core.files import atomic_write, atomic_write_json
from sagonline.core.provenance import digest_file
from sagonline.datasets.base import DatasetError
from sagonline.scene.gaussians import Gaussians
from sagonline.scene.io import SceneFileError, read_scene

TRAINED_SCENE_HELP = (
    "put the trained Gaussian scene at {dir}/{folder}/point_cloud.ply (2DGS or 3DGS layout; "
    "a 3DGS output folder with point_cloud/iteration_*/point_cloud.ply also works), or fit one "
    "with `make scenes{fit}`"
)


SCENES_ROOT = Path(
    os.environ.get("SAGONLINE_SCENES", Path(__file__).resolve().parents[2] / "scenes")
)


def fit_variant(recipe: str | None, seed: int) -> str:
    """The variant name of one draw of a fit recipe: `seed<k>` for a seed other than 0, after
    the recipe's own name where it has one (`<recipe>-seed<k>`); '' for the default recipe's
    seed 0."""
    return "-".join(filter(None, [recipe, f"seed{seed}" if seed else ""]))


def is_variant_name(name: str) -> bool:
    """A fit variant names a folder beside `gaussians/`: letters, digits, '-', '_' and '.',
    never a path ('/', '..', a leading '.')."""
    return bool(re.fullmatch(r"[A-Za-z0-9_][A-Za-z0-9_.-]*", name)) and ".." not in name


def fit_folder(variant: str = "") -> str:
    """The folder of a scene's fit: `gaussians`, or `gaussians-<variant>` for another draw of
    the recipe (`seed1`, ...) or another recipe. A variant that is not a plain name
    (`is_variant_name`) is refused: it would read or write outside the scene's folder."""
    if variant and not is_variant_name(variant):
        raise ValueError(
            f"fit variant {variant!r}: a plain name (letters, digits, - _ .), never a path"
        )
    return f"gaussians-{variant}" if variant else "gaussians"


def gaussians_dir(scene_dir: Path, dataset: str | None = None, variant: str = "") -> Path:
    """Where a scene's trained Gaussians live: `<scene>/gaussians/`, or, for data on a
    read-only disk, `scenes/<dataset>/<scene>/gaussians/` in the project (where `make scenes`
    writes when the data folder is not writable); `gaussians-<variant>/` for a variant."""
    own = scene_dir / fit_folder(variant)
    if own.exists() or dataset is None:
        return own
    overlay = SCENES_ROOT / dataset / scene_dir.name / fit_folder(variant)
    return overlay if overlay.exists() else own


def find_trained_scene(scene_dir: Path, dataset: str | None = None, variant: str = "") -> Path:
    """The scene's `point_cloud.ply`: gaussians/point_cloud.ply, or the latest
    gaussians/point_cloud/iteration_*/point_cloud.ply (in `gaussians_dir`)."""
    base = gaussians_dir(scene_dir, dataset, variant)
    direct = base / "point_cloud.ply"
    if direct.is_file():
        return direct
    iterations = sorted(
        base.glob("point_cloud/iteration_*/point_cloud.ply"),
        key=lambda p: int(re.sub(r"\D", "", p.parent.name) or 0),
    )
    if iterations:
        return iterations[-1]
    # where `make scenes` would write it: the project's overlay for data on a read-only disk
    home = scene_dir
    if dataset is not None and scene_dir.is_dir() and read_only(scene_dir):
        home = SCENES_ROOT / dataset / scene_dir.name
    why = f" ({scene_dir} is read-only)" if home != scene_dir else ""
    raise DatasetError(
        f"no trained scene for {scene_dir.name}: expected "
        f"{home / fit_folder(variant) / 'point_cloud.ply'}{why}; "
        + TRAINED_SCENE_HELP.format(
            dir=home, folder=fit_folder(variant), fit=fit_args(dataset, variant)
        )
    )


def read_only(folder: Path) -> bool:
    """A folder whose owner-write bit is off: read-only for the project even for root (who
    could write anyway), so shared, read-only data is never modified."""
    return not (folder.stat().st_mode & stat.S_IWUSR)


def fit_args(dataset: str | None, variant: str = "") -> str:
    """What to add to `make scenes` to fit this dataset's scene in `variant`'s folder."""
    seed = re.fullmatch(r"seed(\d+)", variant or "")
    args = f"seed={seed.group(1)}" if seed else (f"variant={variant}" if variant else "")
    return (f" DATASET={dataset}" if dataset else "") + (f" ARGS={args}" if args else "")


def photographs_fitted(scene_dir: Path, dataset: str | None = None, variant: str = "") -> int:
    """Every how many of its training photographs the scene's fit was made from: its
    fit_config.json's `train_every` (2: the sparse-photograph protocol); 1 where the fit used
    them all, or records no such setting (a fit of another tool, an older fit)."""
    try:
        path = find_trained_scene(scene_dir, dataset, variant).parent / "fit_config.json"
        every = json.loads(path.read_text()).get("train_every", 1)
    except (DatasetError, OSError, ValueError, AttributeError):
        return 1
    return every if isinstance(every, int) and every >= 1 else 1


def fit_record(scene_dir: Path, dataset: str | None = None, variant: str = "") -> dict | None:
    """What `make scenes` recorded about the trained scene (iterations, why it stopped, PSNR),
    or None for a scene it did not fit."""
    path = find_trained_scene(scene_dir, dataset, variant).parent / "fit_metrics.json"
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    keys = (
        "iterations",
        "iterations_planned",
        "stopped",
        "psnr_train",
        "psnr_heldout",
        "psnr_heldout_object",
        "seed",
        "scene_digest",
    )
    return {k: record[k] for k in keys if k in record} | {"path": str(path)}


def load_trained_scene(
    scene_dir: Path, dataset: str | None = None, drop_nonfinite: bool = False, variant: str = ""
) -> Gaussians:
    """The scene's trained Gaussians; NaN/Inf (or overflowing) rows fail the scene unless
    `drop_nonfinite` (the adapters' `drop_nonfinite` setting) drops them."""
    path = find_trained_scene(scene_dir, dataset, variant)
    try:
        return read_scene(path, drop_nonfinite=drop_nonfinite)
    except SceneFileError as exc:
        raise DatasetError(str(exc)) from exc


def output_dir(scene_dir: Path, dataset: str, variant: str = "") -> Path:
    """`<scene>/gaussians/` (`gaussians-<variant>/`) when the data folder is writable, else the
    project's overlay (a `read_only` data folder, or one that refuses a file)."""
    own = scene_dir / fit_folder(variant)
    if read_only(scene_dir):
        return SCENES_ROOT / dataset / scene_dir.name / fit_folder(variant)
    try:
        own.mkdir(parents=True, exist_ok=True)
        probe = own / ".write_test"
        probe.write_text("")
        probe.unlink()
        return own
    except OSError:
        return SCENES_ROOT / dataset / scene_dir.name / fit_folder(variant)


def foreign_scene(out: Path) -> Path | None:
    """A point_cloud.ply in `out` that is not the one a fit of ours wrote there: ours are the
    files whose digest the fit_metrics.json beside them records. Anything else (the user's
    own scene, also with an interrupted fit's checkpoint beside it) is never replaced silently."""
    scene = out / "point_cloud.ply"
    if not scene.is_file():
        return None
    try:
        recorded = json.loads((out / "fit_metrics.json").read_text()).get("scene_digest")
    except (OSError, ValueError, AttributeError):
        recorded = None
    return None if recorded == digest_file(scene) else scene


def copy_fit(base: Path, out: Path, fit_config: dict) -> dict:
    """The fit in `base` written to `out` as this recipe's (its fit_config.json records this
    recipe, `fit_config`, as a dict; fit_metrics.json says where the fit ran); returns the
    metrics."""
    for path in sorted(base.iterdir()):
        if path.suffix in (".ply", ".png") or path.name == "cameras.json":
            atomic_write(out / path.name, lambda tmp, p=path: shutil.copyfile(p, tmp))
    metrics = json.loads((base / "fit_metrics.json").read_text())
    metrics["same_fit_as"] = base.name  # a sibling folder of `out`
    atomic_write_json(out / "fit_config.json", fit_config)
    atomic_write_json(out / "fit_metrics.json", metrics)
    return metrics


def check_photographs_of_the_fit(
    scene_file: Path, scene_dir: Path, photographs: list[str], expected: int | None
) -> None:
    """Where the protocol does not pin the number of photographs (a capture of one's own), the
    fit does: it records how many it was made from (fit_metrics.json `images`). Fewer here (a
    photograph lost since) would move views from the photographed group to the mask-only one
    without a word; more are fine (a fit of some of them)."""
    if expected is not None:
        return
    record = scene_file.parent / "fit_metrics.json"
    try:
        fitted = json.loads(record.read_text()).get("images")
    except (OSError, ValueError, AttributeError):
        return
    if isinstance(fitted, int) and fitted > len(photographs):
        raise DatasetError(
            f"{scene_dir}: {len(photographs)} photographs of the scene's views, its fit "
            f"({record}) was made from {fitted}: a missing photograph moves its view to the "
            "mask-only group; restore it, or fit again"
        )
