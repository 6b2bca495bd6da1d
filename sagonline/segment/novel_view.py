"""The 2D segmenter answering on a view it has not watched (the paper's initial mode).

A video segmenter tracks objects through a video; a novel view is one more frame of that
video. It is answered as a two-frame video: the nearest trajectory frame (another view than the
one asked for), prompted with the segmenter's own mask there (mask and one click per object),
then the view. Automatic and text-prompted segmenters get the scene's own prompt instead.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from sagonline.scene.cameras import Camera
from sagonline.scene.io.images import resize_nearest
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import ObjectPrompt, Prompt


class NovelViewSegmenter:
    """A segmenter plus what it saw along the trajectory.

    frames: T (H, W, 3) uint8 renders; masks: T (H, W) label-id answers of the segmenter on them;
    cameras: their T cameras; prompt: the scene's prompt; ground_truth: T (H, W) label maps
    (the oracle reads them)."""

    def __init__(
        self,
        segmenter: VideoSegmenter,
        frames: list[np.ndarray],
        masks: list[np.ndarray],
        cameras: list[Camera],
        prompt: Prompt,
        ground_truth: list[np.ndarray] | None = None,
    ):
        if not (len(frames) == len(masks) == len(cameras)) or not frames:
            raise ValueError(
                f"novel views need as many frames ({len(frames)}), masks ({len(masks)}) and "
                f"cameras ({len(cameras)}) as the trajectory has, at least one"
            )
        self.segmenter, self.frames, self.masks = segmenter, frames, masks
        self.cameras, self.prompt, self.ground_truth = cameras, prompt, ground_truth
        self.centres = torch.stack([c.center for c in cameras])

    def nearest(self, camera: Camera) -> int:
        """The trajectory frame nearest `camera` by camera centre, never a frame of the same
        name (that frame's own answer would be copied, not a new one made)."""
        dist = (self.centres - camera.center).norm(dim=1)
        for i, cam in enumerate(self.cameras):
            if cam.name == camera.name and len(self.cameras) > 1:
                dist[i] = float("inf")
        return int(dist.argmin())

    def view_prompt(self, k: int) -> Prompt:
        """The prompt on frame 0 of the two-frame video: the segmenter's mask of frame k, per
        object, with a click at the object's most interior pixel."""
        if not self.prompt.objects:  # automatic or text: the scene's own prompt
            return Prompt(frame=0, texts=list(self.prompt.texts))
        objects = []
        for obj in self.prompt.objects:
            mask = self.masks[k] == obj.label
            if not mask.any():
                continue
            depth = cv2.distanceTransform(np.pad(mask, 1).astype(np.uint8), cv2.DIST_L2, 3)
            y, x = np.unravel_index(int(depth[1:-1, 1:-1].argmax()), mask.shape)
            objects.append(
                ObjectPrompt(
                    obj.label,
                    points=np.array([[x, y]], np.float32),
                    point_labels=np.array([1], np.int64),
                    mask=mask,
                )
            )
        return Prompt(frame=0, objects=objects)

    def answer(
        self, rgb: np.ndarray, camera: Camera, ground_truth: np.ndarray | None = None
    ) -> np.ndarray:
        """(H, W) int64 labels of the view rendered as rgb (H, W, 3) uint8 from `camera`;
        ground_truth: its (H, W) label map, read by the oracle only."""
        k = self.nearest(camera)
        prompt = self.view_prompt(k)
        if self.prompt.objects and not prompt.objects:  # every object lost at frame k
            return np.zeros(rgb.shape[:2], np.int64)
        shape = tuple(rgb.shape[:2])
        frame = self.frames[k]
        if frame.shape[:2] != shape:  # the view renders at another size than the trajectory
            frame = cv2.resize(frame, shape[::-1], interpolation=cv2.INTER_AREA)
            for obj in prompt.objects:
                obj.mask = resize_nearest(obj.mask.astype(np.uint8), shape).astype(bool)
                obj.points = obj.points * np.array([shape[1], shape[0]]) / self.masks[k].shape[::-1]
        truth = None
        if self.ground_truth is not None and ground_truth is not None:
            truth = [
                resize_nearest(self.ground_truth[k], shape),
                resize_nearest(ground_truth, shape),
            ]
        result = self.segmenter.segment([frame, rgb], prompt, ground_truth=truth)
        return result.masks[1]
