"""The fits table (`python -m bench.tables.report --fits`): every fit_metrics.json `make scenes`
wrote, its recipe against today's defaults, and each fit's held-out renders in one image."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pandas as pd
from PIL import Image

from bench import ROOT
from sagonline.core.files import atomic_write_image, atomic_write_text
from sagonline.datasets.fits import SCENES_ROOT
from sagonline.fitting import FitConfig

FIT_COLUMNS = [
    "dataset",
    "scene",
    "kind",
    "recipe",
    "init",
    "resolution",
    "images",
    "iterations",
    "gaussians",
    "fit_seconds",
    "psnr_train",
    "psnr_heldout",
    "psnr_heldout_object",
    "heldout_views",
    "folder",
]


def fit_recipe(cfg: dict) -> str:
    """The fit settings that differ from today's defaults ("default" if none), the automatic
    camera clearance and the device left out; settings newer than the fit are named after
    "predates:" (the fit ran without them)."""
    defaults = {
        k: v for k, v in asdict(FitConfig()).items() if k not in ("camera_clearance", "device")
    }
    changed = [
        f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
        for k, v in cfg.items()
        if k in defaults
        and v != defaults[k]
        and not (isinstance(v, list) and tuple(v) == defaults[k])
    ]
    missing = [k for k in defaults if k not in cfg]
    if missing:
        changed.append("predates: " + " ".join(missing))
    return " ".join(changed) or "default"


def fit_rows(roots: list[Path]) -> pd.DataFrame:
    """One row per fitted scene: its fit_metrics.json, and the kind and recipe from
    fit_config.json."""
    rows = []
    for path in sorted({p for r in roots if r.exists() for p in r.rglob("fit_metrics.json")}):
        m = json.loads(path.read_text())
        cfg_path = path.with_name("fit_config.json")
        cfg = json.loads(cfg_path.read_text()) if cfg_path.is_file() else {}
        folder = path.parent
        rows.append(
            {
                **{k: m.get(k) for k in FIT_COLUMNS},
                "scene": folder.parent.name,  # the folder holding gaussians/ (copies rename it)
                "kind": cfg.get("kind"),
                "recipe": fit_recipe(cfg),
                "resolution": "x".join(map(str, m.get("resolution", []))),
                "heldout_views": " ".join(m.get("heldout_views", [])),
                "folder": str(folder.relative_to(ROOT))
                if folder.is_relative_to(ROOT)
                else str(folder),
            }
        )
    return pd.DataFrame(rows, columns=FIT_COLUMNS)


def stack_heldout_renders(folder: Path, out: Path) -> Path | None:
    """The held-out render | photo pairs `make scenes` wrote, stacked into one JPEG in `out`."""
    pairs = sorted(folder.glob("heldout_*.png"))
    if not pairs:
        return None
    rows = [np.asarray(Image.open(p).convert("RGB")) for p in pairs]
    width = min(r.shape[1] for r in rows)
    metrics = json.loads((folder / "fit_metrics.json").read_text())
    name = f"fit_{metrics.get('dataset', 'scene')}_{folder.parent.name}"
    return atomic_write_image(
        out / f"{name}_heldout.jpg", np.concatenate([r[:, :width] for r in rows])
    )


def write_fits(out: Path) -> None:
    """reports/fits.{md,csv} and each fit's held-out renders (`--fits`)."""
    fits = fit_rows([SCENES_ROOT, ROOT / "datasets"])
    if fits.empty:
        print(f"no fitted scenes under {SCENES_ROOT} or datasets/: run `make scenes` first")
        return
    atomic_write_text(out / "fits.csv", fits.to_csv(index=False))
    atomic_write_text(
        out / "fits.md",
        "# Fitted scenes (`make scenes`)\n\n- PSNR in dB on the training views, the held-out "
        "views (every 8th by name) and, where the dataset has object masks, inside them.\n"
        "- recipe: the fit's settings that differ from today's defaults "
        "(`sagonline.fitting.FitConfig`); `predates:` names settings the fit ran without.\n\n"
        + fits.to_markdown(index=False, floatfmt=".4g")
        + "\n",
    )
    for folder in fits["folder"]:
        stack_heldout_renders(ROOT / folder, out)
    print(f"{len(fits)} fitted scenes -> {out}/fits.md, fits.csv")
