"""A SAM-family image encoder's call, queued (`queue_encoder`), and the next view's call started
while the host still prompts this one (`EncodeAhead`, `segmenter.encode_ahead`).

Stage I follows its views one after another: a view's embedding, then its prompts decoded in up
to three dependent rounds, then its vote. Only the encoder's input, the rendered frame, is known
a view early. With encode_ahead, the encoder's kernels of the next view (and the copies of its
outputs to the host) are queued on a side stream of the GPU before this view's prompts are
decoded, and `SamPair.embed` of that view later waits for them (an event), not for the GPU: the
encoder's GPU time can run under the host's prompting, the decoder's small calls and the vote,
whose own GPU work is a few ms of a view's. Without CUDA the call runs when it is started (the same
embeddings, in another order; nothing overlaps).

Streams: the side stream waits for the work queued before each start, an encoder call on the
current stream waits for the side stream (`before_encoding`: a CUDA graph's input buffers are
the same for both), and outputs taken onto the current stream are recorded there, so the
caching allocator reuses none of their memory while that stream may still read it.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

STARTED_AT_MOST = 2  # frames started and not yet taken; an older one is dropped


@dataclass
class Encoded:
    """One encoder call's outputs on their way to the host: copies ([1, ...] each, numpy, or
    host tensors still being filled), the same values on the device by output name where the
    decoder reads them there (float32), and the CUDA event recorded after the copies (None:
    they are filled)."""

    copies: list
    on_device: dict = field(default_factory=dict)
    done: Any = None

    def arrays(self) -> list[np.ndarray]:  # [1, ...] each
        """The outputs on the host, once their copies are done (waits for this call alone)."""
        if self.done is not None:
            self.done.synchronize()
        return [c if isinstance(c, np.ndarray) else c.numpy() for c in self.copies]


def queue_encoder(pair: Any, image: np.ndarray) -> Encoded:  # pair: a `sam_onnx.SamPair`
    """The encoder's call on an RGB uint8 (H, W, 3) image, queued on the current stream: its
    outputs rounded to the pair's stored type and their copies to the host queued (into pinned
    memory), and where both halves run on PyTorch on one device, the same values there in
    float32 by output name (what the decoder reads: no copy to the host and back). A PyTorch
    encoder off the CPU gets its frame made on its device (`preprocess_on`); on the CPU, the
    host's (numpy's per-plane work is faster there, and nothing is copied)."""
    name = pair.encoder.get_inputs()[0].name
    device = getattr(pair.encoder, "device", None)
    if device is None:  # onnxruntime: done when it returns
        return Encoded(pair.encoder.run(None, {name: pair.preprocess(image)}))
    import torch

    if device.type == "cpu":
        frame = torch.from_numpy(pair.preprocess(image))
    else:
        frame = pair.preprocess_on(image, device)
    outputs = pair.encoder.forward({name: frame})
    on_device: dict = {}
    if pair.decoder_runtime != "torch" or device != getattr(pair.decoder, "device", None):
        outputs = [o.float() for o in outputs]
    else:
        stored = getattr(torch, np.dtype(pair.stored_dtype).name)  # float16 or float32
        outputs = [o.float().to(stored) for o in outputs]
        on_device = {n: o.float() for n, o in zip(pair.outputs, outputs, strict=True)}
    if device.type == "cpu":
        return Encoded(list(outputs), on_device)
    copies = [o.detach().to("cpu", non_blocking=True) for o in outputs]
    done = torch.cuda.Event()
    done.record(torch.cuda.current_stream(device))
    return Encoded(copies, on_device, done)


class EncodeAhead:
    """Encoder calls started for frames a later `SamPair.embed` asks for, by cache key; on a
    CUDA `device` queued on a side stream."""

    def __init__(self, device: Any = None):  # torch.device or None (onnxruntime)
        self.stream = None
        if device is not None and device.type == "cuda":
            import torch

            self.stream = torch.cuda.Stream(device)
        self.started: OrderedDict[str, Encoded] = OrderedDict()
        self.frames: dict[str, tuple[np.ndarray, str]] = {}  # by key: the frame, its digest

    def start(
        self,
        key: str,
        encode: Callable[[], Encoded],
        frame: np.ndarray | None = None,  # [H, W, 3] the frame encoded, known by identity
        frame_digest: str = "",
    ) -> None:
        """`encode()` for the frame of `key` (once), on the side stream after the work queued
        so far; without one, now. The oldest past `STARTED_AT_MOST` is dropped."""
        if key in self.started:
            return
        if frame is not None:
            self.frames[key] = (frame, frame_digest)
        if self.stream is None:
            self.started[key] = encode()
        else:
            import torch

            self.stream.wait_stream(torch.cuda.current_stream(self.stream.device))
            with torch.cuda.stream(self.stream):
                self.started[key] = encode()
        while len(self.started) > STARTED_AT_MOST:
            dropped, _ = self.started.popitem(last=False)
            self.frames.pop(dropped, None)

    def named(self, frame: np.ndarray) -> tuple[str, str] | None:
        """The digest and key of the call started for this very array (the same object, not
        an equal one: its `embed` digests it no second time, ~1 ms a 960x540 view), or None."""
        for key, (started, frame_digest) in self.frames.items():
            if started is frame:
                return frame_digest, key
        return None

    def take(self, key: str) -> Encoded | None:
        """The call started for `key` (None: none was), its device outputs recorded on the
        current stream that reads them from now on."""
        self.frames.pop(key, None)
        encoded = self.started.pop(key, None)
        if encoded is not None and self.stream is not None:
            import torch

            current = torch.cuda.current_stream(self.stream.device)
            current.wait_event(encoded.done)
            for tensor in encoded.on_device.values():
                tensor.record_stream(current)
        return encoded

    def before_encoding(self) -> None:
        """An encoder call about to be queued on the current stream waits (on the GPU) for any
        started on the side stream."""
        if self.stream is not None:
            import torch

            torch.cuda.current_stream(self.stream.device).wait_stream(self.stream)
