"""A weight-free video segmenter: colour models + optical-flow priors + watershed (OpenCV).

Prompt frame: object masks are used as given (unless `use_masks` is off); boxes and clicks
seed GrabCut, each click adding what it says: a positive click's region of like colour (its
chromaticity, its brightness within a factor) is probable foreground (its disc definite), a
negative click's region definite background, the image border background where no click's
region reaches it. Each label (background included) gets a colour histogram (16^3
bins) from that frame.
Then, frame by frame, forwards and backwards from the prompt frame:
1. dense optical flow (Farneback) from the new frame back to the previous one warps the
   previous label map onto the new frame;
2. each pixel takes the label maximising colour likelihood x spatial prior, the prior
   decaying with the distance to that label's warped region (`motion_px`), with a floor that
   lets a strongly coloured object come back after an occlusion;
3. every label's region, eroded by `band_px`, seeds `cv2.watershed` on the new image, so
   boundaries snap to image edges instead of drifting with the flow (a region that erodes
   away keeps its innermost pixel);
4. the colour histograms adapt slowly (`adapt`) to the new frame's labels.
A label whose region collapses (a view where the object is hidden or unlike itself) also keeps
the region it had before as its spatial prior (`recover`), so it comes back where its colour
does instead of staying lost for the rest of the video.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sagonline.core.plugins import SEGMENTERS
from sagonline.segment.base import VideoSegmenter
from sagonline.segment.prompts import Prompt


@dataclass
class ClassicalConfig:
    """The weight-free segmenter's settings (`segmenter=classical`)."""

    use_masks: bool = True
    """Start from the prompt's masks where it has them; false: from the clicks alone (GrabCut)."""
    band_px: int = 3
    """Each label's region is eroded by this many pixels before it seeds the watershed."""
    flow_levels: int = 4
    """Pyramid levels of the Farneback optical flow."""
    flow_window: int = 15
    """Window size of the Farneback optical flow, in pixels."""
    grabcut_iters: int = 5
    """GrabCut iterations on the prompt frame (clicks and boxes)."""
    click_radius: int = 4
    """Radius in pixels of the definite disc a click marks."""
    prior_radius: float = 0.25
    """How far a click's region reaches: twice this fraction of the image's shorter side."""
    click_tolerance: float = 0.05
    """A click's region: the connected pixels whose chromaticity (r, g over r + g + b) lies
    within this of the click's own..."""
    click_brightness_ratio: float = 2.0
    """... and whose brightness (r + g + b) within this factor of it, either way: shading and
    texture change the brightness across one surface far more than its hue."""
    motion_px: float = 6.0
    """How fast a label's spatial prior decays with the distance to its warped region (px)."""
    prior_floor: float = 1e-3
    """The prior's floor: a strongly coloured object may come back after an occlusion."""
    adapt: float = 0.02
    """Rate at which the colour histograms adapt to each new frame."""
    bins: int = 16
    """Colour histogram bins per channel."""
    recover: float = 0.5
    """A label whose region moved onto a frame is smaller than this fraction of the last region
    it had before it collapsed (in this pass over the video) also takes its prior from that
    region: it comes back where its colour does instead of staying lost. Where no label's
    region halves from one frame to the next the masks are those without it; 0: off."""

    def __post_init__(self) -> None:
        from sagonline.core.settings import check_settings

        check_settings(
            "segmenter",
            band_px=(self.band_px >= 0, self.band_px, ">= 0"),
            flow_levels=(1 <= self.flow_levels <= 10, self.flow_levels, "in [1, 10]"),
            flow_window=(3 <= self.flow_window <= 255, self.flow_window, "in [3, 255]"),
            grabcut_iters=(1 <= self.grabcut_iters <= 100, self.grabcut_iters, "in [1, 100]"),
            click_radius=(self.click_radius >= 1, self.click_radius, ">= 1"),
            prior_radius=(0 < self.prior_radius <= 1, self.prior_radius, "in (0, 1]"),
            click_tolerance=(0 < self.click_tolerance <= 1, self.click_tolerance, "in (0, 1]"),
            click_brightness_ratio=(
                self.click_brightness_ratio >= 1,
                self.click_brightness_ratio,
                ">= 1",
            ),
            motion_px=(self.motion_px > 0, self.motion_px, "> 0"),
            prior_floor=(0 <= self.prior_floor < 1, self.prior_floor, "in [0, 1)"),
            recover=(0 <= self.recover <= 1, self.recover, "a fraction in [0, 1]"),
            adapt=(0 <= self.adapt <= 1, self.adapt, "in [0, 1]"),
            bins=(2 <= self.bins <= 64, self.bins, "in [2, 64]"),
        )


@SEGMENTERS.register("classical", ClassicalConfig)
class FlowWatershedSegmenter(VideoSegmenter):
    """Weight-free: colour models, optical-flow priors and watershed (OpenCV)."""

    name = "classical"

    def __init__(
        self,
        band_px: int = 3,
        flow_levels: int = 4,
        flow_window: int = 15,
        grabcut_iters: int = 5,
        click_radius: int = 4,
        prior_radius: float = 0.25,
        motion_px: float = 6.0,
        prior_floor: float = 1e-3,
        adapt: float = 0.02,
        bins: int = 16,
        use_masks: bool = True,
        click_tolerance: float = 0.05,
        click_brightness_ratio: float = 2.0,
        recover: float = 0.5,
    ):
        self.band_px, self.flow_levels, self.flow_window = band_px, flow_levels, flow_window
        self.grabcut_iters, self.click_radius = grabcut_iters, click_radius
        self.prior_radius, self.motion_px, self.prior_floor = prior_radius, motion_px, prior_floor
        self.adapt, self.bins, self.use_masks = adapt, bins, use_masks
        self.click_tolerance = click_tolerance
        self.click_brightness_ratio = click_brightness_ratio
        self.recover = recover
        self.reads = ("masks", "clicks", "boxes") if use_masks else ("clicks", "boxes")
        self.hists: dict[int, np.ndarray] = {}

    # --- prompt frame -------------------------------------------------------------------------
    def initial_labels(self, frame: np.ndarray, prompt: Prompt) -> np.ndarray:
        h, w = frame.shape[:2]
        labels = np.zeros((h, w), np.int64)
        if not prompt.objects:
            raise ValueError(
                "the classical segmenter needs clicks, boxes or masks on the prompt "
                "frame (it does not read text prompts)"
            )
        for obj in prompt.objects:
            if obj.mask is not None and self.use_masks:
                m = np.asarray(obj.mask, bool)
                if m.shape != (h, w):
                    raise ValueError(
                        f"prompt mask of object {obj.label} is {m.shape}, frame is {(h, w)}"
                    )
            else:
                m = self._grabcut(frame, obj)
            labels[m] = obj.label
        return labels

    def _grabcut(self, frame: np.ndarray, obj) -> np.ndarray:
        """GrabCut seeded by a box and/or clicks. Each click adds what it says: a positive
        click makes the region of like colour around it (`click_region`) probable foreground
        and its disc definite foreground; a negative click makes the region it lies in definite
        background. The image border is background (without a box) where no click's region
        reaches it."""
        h, w = frame.shape[:2]
        bgr = np.ascontiguousarray(frame[..., ::-1])
        gc = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
        if obj.box is not None:
            x0, y0, x1, y1 = (int(round(v)) for v in obj.box)
            gc[:] = cv2.GC_BGD
            gc[max(y0, 0) : y1, max(x0, 0) : x1] = cv2.GC_PR_FGD
        pts = np.zeros((0, 2)) if obj.points is None else np.asarray(obj.points).reshape(-1, 2)
        lab = np.ones(len(pts), int) if obj.point_labels is None else np.asarray(obj.point_labels)
        colour = chromaticity_and_brightness(frame)
        for (x, y), v in zip(pts, lab, strict=True):
            if v > 0:
                region = self.click_region(colour, (int(x), int(y)))
                gc[region & (gc != cv2.GC_BGD)] = cv2.GC_PR_FGD
        for (x, y), v in zip(pts, lab, strict=True):  # negatives win over positives' regions
            if v <= 0:
                gc[self.click_region(colour, (int(x), int(y)))] = cv2.GC_BGD
        for (x, y), v in zip(pts, lab, strict=True):
            cv2.circle(
                gc, (int(x), int(y)), self.click_radius, cv2.GC_FGD if v > 0 else cv2.GC_BGD, -1
            )
        if obj.box is None:
            border = max(2, min(h, w) // 40)
            for sl in (np.s_[:border], np.s_[-border:]):  # what no click's region reaches
                gc[sl][gc[sl] == cv2.GC_PR_BGD] = cv2.GC_BGD
                gc[:, sl][gc[:, sl] == cv2.GC_PR_BGD] = cv2.GC_BGD
        if not (gc == cv2.GC_FGD).any() and not (gc == cv2.GC_PR_FGD).any():
            raise ValueError(f"object {obj.label}: no positive click or box to start from")
        bgd, fgd = np.zeros((1, 65)), np.zeros((1, 65))
        # GrabCut's k-means draws from OpenCV's per-thread RNG: seeded here, the same prompt gives
        # the same mask in any thread and after any earlier call (the viewer's worker thread)
        cv2.setRNGSeed(0x5A6)
        cv2.grabCut(bgr, gc, None, bgd, fgd, self.grabcut_iters, cv2.GC_INIT_WITH_MASK)
        return (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)

    def click_region(self, colour: np.ndarray, xy: tuple[int, int]) -> np.ndarray:
        """(H, W) bool: the pixels of like colour connected to the click (`click_region`)."""
        return click_region(
            colour, xy, self.click_tolerance, self.click_brightness_ratio, self.prior_radius
        )

    def _bin_index(self, frame: np.ndarray) -> np.ndarray:
        q = (frame.astype(np.int64) * self.bins) // 256
        return (q[..., 0] * self.bins + q[..., 1]) * self.bins + q[..., 2]

    def fit_colors(self, frame: np.ndarray, labels: np.ndarray, rate: float = 1.0) -> None:
        """Per-label colour histograms (Laplace-smoothed), blended in with weight `rate`."""
        idx = self._bin_index(frame)
        for lab in np.unique(labels):
            h = np.bincount(idx[labels == lab], minlength=self.bins**3).astype(np.float64) + 1.0
            h /= h.sum()
            old = self.hists.get(int(lab))
            self.hists[int(lab)] = h if old is None or rate >= 1.0 else (1 - rate) * old + rate * h

    def classify(
        self,
        frame: np.ndarray,  # [H, W, 3] uint8 RGB
        warped: np.ndarray,  # [H, W] int64: the previous labels moved onto this frame
        last_seen: dict[int, np.ndarray] | None = None,  # label -> [H, W] bool
    ) -> np.ndarray:  # [H, W] int64
        """argmax over labels of log colour likelihood + log distance prior: the distance to the
        label's warped region, and for a label whose warped region collapsed (below `recover`
        times its `last_seen` region) to that region too."""
        idx = self._bin_index(frame)
        labs = sorted(self.hists)
        scores = np.empty((len(labs), *warped.shape))
        for k, lab in enumerate(labs):
            region = warped == lab
            known = last_seen.get(lab) if last_seen is not None else None
            if known is not None and region.sum() < self.recover * known.sum():
                region = region | known
            outside = (~region).astype(np.uint8)
            dist = cv2.distanceTransform(outside, cv2.DIST_L2, 3)
            prior = np.maximum(np.exp(-dist / self.motion_px), self.prior_floor)
            scores[k] = np.log(self.hists[lab][idx]) + np.log(prior)
        return np.asarray(labs)[scores.argmax(0)]

    def propagate(
        self,
        prev_frame: np.ndarray,  # [H, W, 3] uint8 RGB
        frame: np.ndarray,  # [H, W, 3] uint8 RGB
        prev_labels: np.ndarray,  # [H, W] int64
        last_seen: dict[int, np.ndarray] | None = None,  # label -> [H, W] bool
    ) -> np.ndarray:  # [H, W] int64
        """Labels of `frame` from the labels of the frame before it in video order (and, for a
        label that collapsed, the region it had before: `recover`)."""
        g0 = cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)
        g1 = cv2.cvtColor(prev_frame, cv2.COLOR_RGB2GRAY)
        flow = cv2.calcOpticalFlowFarneback(
            g0, g1, None, 0.5, self.flow_levels, self.flow_window, 3, 7, 1.5, 0
        )
        h, w = g0.shape
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        warped = cv2.remap(
            prev_labels.astype(np.float32),
            gx + flow[..., 0],
            gy + flow[..., 1],
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.int64)
        labels = self.refine(frame, self.classify(frame, warped, last_seen))
        self.fit_colors(frame, labels, self.adapt)
        return labels

    def refine(self, frame: np.ndarray, labels: np.ndarray) -> np.ndarray:
        """Snap label boundaries to image edges: eroded regions seed a watershed."""
        markers = np.zeros(labels.shape, np.int32)
        kernel = cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * self.band_px + 1, 2 * self.band_px + 1)
        )
        for lab in np.unique(labels):
            region = (labels == lab).astype(np.uint8)
            core = cv2.erode(region, kernel)
            if not core.any():
                dist = cv2.distanceTransform(region, cv2.DIST_L2, 3)
                core = (dist == dist.max()) & (region > 0)
            markers[core > 0] = int(lab) + 1
        cv2.watershed(np.ascontiguousarray(frame[..., ::-1]), markers)
        out = markers.astype(np.int64) - 1
        unresolved = out < 0  # ridges (-1) and any pixel no marker reached
        out[unresolved] = labels[unresolved]
        return out

    def _segment(self, frames, prompt: Prompt, ground_truth):
        import time

        masks: list[np.ndarray | None] = [None] * len(frames)
        seconds = [0.0] * len(frames)
        start = time.perf_counter()
        for t, mask in self._stream(frames, prompt, ground_truth):
            masks[t] = mask
            seconds[t] = time.perf_counter() - start
            start = time.perf_counter()
        return masks, seconds

    def _stream(self, frames, prompt: Prompt, ground_truth=None):
        """The prompt frame, then forwards to the end, then backwards from the prompt frame."""
        n = len(frames)
        masks: list[np.ndarray | None] = [None] * n
        masks[prompt.frame] = self.initial_labels(frames[prompt.frame], prompt)
        self.hists = {}
        self.fit_colors(frames[prompt.frame], masks[prompt.frame])
        initial = dict(self.hists)
        last_seen = seen_at_prompt = remember({}, masks[prompt.frame])
        yield prompt.frame, masks[prompt.frame]
        order = list(range(prompt.frame + 1, n)) + list(range(prompt.frame - 1, -1, -1))
        for t in order:
            if t == prompt.frame - 1:  # the backward pass starts from the prompt frame
                self.hists, last_seen = dict(initial), seen_at_prompt
            src = t - 1 if t > prompt.frame else t + 1
            masks[t] = self.propagate(frames[src], frames[t], masks[src], last_seen)
            last_seen = remember(last_seen, masks[t], self.recover)
            yield t, masks[t]


def remember(
    last_seen: dict[int, np.ndarray],  # label -> [H, W] bool
    labels: np.ndarray,  # [H, W] int64
    collapse: float = 0.0,
) -> dict[int, np.ndarray]:
    """`last_seen` with each label of `labels` at its region there, unless that region is
    smaller than `collapse` times the one remembered (a collapse is not remembered)."""
    out = dict(last_seen)
    for lab in np.unique(labels):
        region, known = labels == lab, last_seen.get(int(lab))
        if known is None or region.sum() >= collapse * known.sum():
            out[int(lab)] = region
    return out


def click_region(
    colour: np.ndarray,  # [H, W, 3] `chromaticity_and_brightness` of the frame
    xy: tuple[int, int],
    tolerance: float = 0.05,
    brightness_ratio: float = 2.0,
    prior_radius: float = 0.25,
) -> np.ndarray:  # [H, W] bool
    """The pixels connected to the click whose colour lies near the click's own (a flood fill
    from it: chromaticity within `tolerance`, brightness within a factor `brightness_ratio`),
    within `prior_radius` of the image's shorter side (times two) around it."""
    h, w = colour.shape[:2]
    x, y = min(max(int(xy[0]), 0), w - 1), min(max(int(xy[1]), 0), h - 1)
    mask = np.zeros((h + 2, w + 2), np.uint8)
    tol = (tolerance, tolerance, float(np.log(brightness_ratio)))
    flags = 4 | cv2.FLOODFILL_MASK_ONLY | cv2.FLOODFILL_FIXED_RANGE | (1 << 8)
    cv2.floodFill(colour.copy(), mask, (x, y), 0, tol, tol, flags)
    region = mask[1:-1, 1:-1] > 0
    reach = np.zeros((h, w), np.uint8)
    cv2.circle(reach, (x, y), int(prior_radius * min(h, w) * 2), 1, -1)
    return region & (reach > 0)


def chromaticity_and_brightness(frame: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (H, W, 3) float32: r / s, g / s and log s, with s = r + g + b
    (+ 3, so black is a colour too). Shading scales s and leaves r / s, g / s alone. Computed a
    plane at a time (a tenth of the time of the interleaved arrays, the same values)."""
    r, g, b = (plane.astype(np.float32) + 1.0 for plane in cv2.split(np.ascontiguousarray(frame)))
    total = r + g
    total += b
    return cv2.merge([r / total, g / total, np.log(total)])
