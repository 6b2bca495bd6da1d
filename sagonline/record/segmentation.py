"""The rerun recording of `sagonline segment`: a layout of its own, every panel filled.

- `segment/view/camera`: each trajectory view (Transform3D + Pinhole, OpenCV axes) on the
  `frame` timeline, with its render (`rgb`), the clicks drawn on the prompt frame (`clicks`:
  positive green, negative red, named by object), the 2D segmenter's mask (`segmenter`) and
  the fused labels rendered (`labels`);
- `segment/scene/splats`: the scene as Gaussian splats (`GaussianSplats3D`), each coloured by
  its label with its own opacity, unlabelled ones grey and faint;
- `segment/scene/legend`: one labelled point per label at its Gaussians' centre (the legend).

One AnnotationContext names and colours the labels everywhere. Open with
`rerun recording.rrd`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sagonline.labels.colours import BACKGROUND_3D, label_colors

UNLABELLED = (140, 140, 140)


def record_segmentation(
    path: str | Path,
    gaussians,
    labels: np.ndarray,
    names: list[str],
    cameras: list,
    frames: list[np.ndarray],
    masks: list[np.ndarray],
    label_renders: list[np.ndarray],
    prompt: dict,
    prompt_frame: int,
) -> None:
    """Write the recording. labels: (N,) int64 (-1 unlabelled); frames: T (H, W, 3) uint8;
    masks, label_renders: T (H, W) label maps; prompt: labels.json's prompt record (objects
    with their clicks and negatives); prompt_frame: its frame in the trajectory."""
    import rerun as rr

    rec = rr.RecordingStream("sagonline-segment")
    rec.save(str(path), default_blueprint=blueprint())
    colors = label_colors(len(names))
    info = [(i, n, tuple(int(c) for c in colors[i])) for i, n in enumerate(names)]
    rec.log("segment", rr.AnnotationContext(info), static=True)
    for i, (cam, frame, mask, lab) in enumerate(
        zip(cameras, frames, masks, label_renders, strict=True)
    ):
        rec.set_time("frame", sequence=i)
        base = "segment/view/camera"
        w2c = cam.world_to_cam.detach().double().cpu().numpy()
        rec.log(
            base,
            rr.Transform3D(
                translation=w2c[:3, 3],
                mat3x3=w2c[:3, :3],
                relation=rr.TransformRelation.ChildFromParent,
            ),
            rr.Pinhole(
                image_from_camera=cam.K.detach().double().cpu().numpy(),
                resolution=[cam.width, cam.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.2,
            ),
        )
        rec.log(f"{base}/rgb", rr.Image(np.ascontiguousarray(frame)).compress(jpeg_quality=90))
        rec.log(f"{base}/segmenter", rr.SegmentationImage(np.asarray(mask).astype(np.uint16)))
        rec.log(f"{base}/labels", rr.SegmentationImage(np.asarray(lab).astype(np.uint16)))
        rec.log(
            f"{base}/clicks", clicks(prompt) if i == prompt_frame else rr.Clear(recursive=False)
        )
    rec.set_time("frame", sequence=0)
    splats(rec, gaussians, np.asarray(labels), colors)
    legend(rec, gaussians, np.asarray(labels), names)
    rec.flush()
    rec.disconnect()


def clicks(prompt: dict):
    """The prompt's clicks as 2D points: positive green, negative red, labelled by object."""
    import rerun as rr

    xy, col, text = [], [], []
    for obj in prompt.get("objects", []):
        for x, y in obj.get("clicks", []):
            xy.append((x, y)), col.append((40, 220, 60)), text.append(obj["name"])
        for x, y in obj.get("negatives", []):
            xy.append((x, y)), col.append((230, 40, 40)), text.append(f"not {obj['name']}")
    return rr.Points2D(
        np.asarray(xy, np.float32).reshape(-1, 2), colors=col, labels=text, radii=4.0
    )


def splats(rec, gaussians, labels: np.ndarray, colors: np.ndarray) -> None:
    """The scene as splats coloured by label (opacity kept; unlabelled grey at half of it)."""
    import rerun as rr

    g = gaussians.to("cpu")
    scales = g.scales.detach().numpy()
    if scales.shape[1] == 2:  # surfels: a thin third axis
        scales = np.concatenate([scales, scales.min(1, keepdims=True) * 1e-2], 1)
    palette = colors.copy()
    palette[0] = BACKGROUND_3D
    rgb = np.where((labels >= 0)[:, None], palette[labels.clip(0)], np.array(UNLABELLED))
    alpha = g.opacities.detach().numpy() * np.where(labels >= 0, 1.0, 0.5)
    rgba = np.concatenate([rgb, (alpha * 255)[:, None]], 1).astype(np.uint8)
    rec.log(
        "segment/scene/splats",
        rr.GaussianSplats3D(
            centers=g.means.detach().numpy(),
            scales=scales,
            quaternions=g.quats.detach().numpy()[:, [1, 2, 3, 0]],  # wxyz -> xyzw
            colors=rgba,
        ),
        static=True,
    )


def legend(rec, gaussians, labels: np.ndarray, names: list[str]) -> None:
    """One point per label (its Gaussians' centre), named: the 3D view's legend."""
    import rerun as rr

    means = gaussians.means.detach().cpu().numpy()
    ids = [k for k in range(len(names)) if (labels == k).any()]
    centres = np.asarray([means[labels == k].mean(0) for k in ids], np.float32).reshape(-1, 3)
    rec.log(
        "segment/scene/legend",
        rr.Points3D(
            centres,
            class_ids=np.asarray(ids, np.uint16),
            labels=[names[k] for k in ids],
            radii=0.01,
        ),
        static=True,
    )


def blueprint():
    """RGB with the clicks | the segmenter's mask | the fused labels, beside the 3D scene."""
    import rerun.blueprint as rrb

    cam = "/segment/view/camera"
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    name="render + clicks", origin=cam, contents=["$origin/rgb", "$origin/clicks"]
                ),
                rrb.Horizontal(
                    rrb.Spatial2DView(
                        name="2D segmenter",
                        origin=cam,
                        contents=["$origin/rgb", "$origin/segmenter"],
                    ),
                    rrb.Spatial2DView(
                        name="fused labels", origin=cam, contents=["$origin/rgb", "$origin/labels"]
                    ),
                ),
            ),
            rrb.Spatial3DView(
                name="scene by label",
                origin="/segment",
                contents=["/segment/scene/**", "/segment/view/camera"],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )
