"""Make torchvision importable next to a CPU-only torch (needed by sam2 and ultralytics).

torchvision's PyPI wheels ship a compiled `_C.so` built against CUDA. Beside a CPU build of
torch it fails to load, torchvision then has no `torchvision::` operators, and `import
torchvision` dies in its meta registrations ("operator torchvision::nms does not exist").

`import_torchvision()` imports it normally and, only on that failure, defines the two
operators torchvision registers unconditionally (`nms`, `qnms`) with a pure-PyTorch CPU
non-maximum suppression, imports it again and marks its ops as available. The other compiled
ops (roi_align, deform_conv2d, ...) stay absent and raise torchvision's own error if called;
neither sam2 nor ultralytics' segmentation path calls them. Where torchvision's extension
loads (a matching CUDA machine) nothing is changed.
"""

from __future__ import annotations

import sys

import torch

_shimmed = False
_lib = None  # the torchvision op library, kept alive once defined


def nms_reference(
    boxes: torch.Tensor,  # [N, 4] x1, y1, x2, y2
    scores: torch.Tensor,  # [N]
    iou_threshold: float,
) -> torch.Tensor:  # [K] kept indices, by score
    """Greedy NMS. boxes: (N, 4) x1, y1, x2, y2; scores: (N,). Returns kept indices (K,)
    sorted by decreasing score, like torchvision.ops.nms."""
    if boxes.numel() == 0:
        return torch.empty(0, dtype=torch.long, device=boxes.device)
    order = torch.argsort(scores, descending=True)
    b = boxes[order].float()
    area = (b[:, 2] - b[:, 0]).clamp_min(0) * (b[:, 3] - b[:, 1]).clamp_min(0)
    x1 = torch.maximum(b[:, None, 0], b[None, :, 0])
    y1 = torch.maximum(b[:, None, 1], b[None, :, 1])
    x2 = torch.minimum(b[:, None, 2], b[None, :, 2])
    y2 = torch.minimum(b[:, None, 3], b[None, :, 3])
    inter = (x2 - x1).clamp_min(0) * (y2 - y1).clamp_min(0)
    iou = inter / (area[:, None] + area[None, :] - inter).clamp_min(1e-12)
    suppressed = torch.zeros(len(b), dtype=torch.bool, device=b.device)
    keep = []
    for i in range(len(b)):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return order[torch.tensor(keep, dtype=torch.long, device=b.device)]


def _define_cpu_ops() -> None:
    global _shimmed, _lib
    if _shimmed:
        return
    _lib = torch.library.Library("torchvision", "DEF")  # noqa: F841 (kept alive globally)
    for name in ("nms", "qnms"):
        _lib.define(f"{name}(Tensor dets, Tensor scores, float iou_threshold) -> Tensor")
        _lib.impl(name, nms_reference, "CPU")
    _shimmed = True


def import_torchvision():
    """`import torchvision`, working around a compiled extension that cannot load."""
    try:
        import torchvision

        return torchvision
    except RuntimeError as exc:
        if "torchvision::" not in str(exc):
            raise
    for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
        del sys.modules[name]
    _define_cpu_ops()
    import torchvision
    import torchvision.extension

    torchvision.extension._has_ops = lambda: True
    return torchvision
