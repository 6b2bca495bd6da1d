"""The Triton vote kernels (and the tile lists') compiled for a GPU without one: registers per
thread, the stack frame their spilled registers take, shared memory, and the blocks an SM can
hold, per kernel and rule.

    python -m bench.speed.kernel_resources [--arch 90] [--labels 3] [--kernels walk,chunk16]
                                           [--out F.csv] [--quick]

Triton compiles for a named target on any machine (its wheel carries ptxas and cuobjdump), so
this runs on the CPU: a kernel that does not compile for CUDA is caught here, and what bounds
its occupancy (registers, shared memory) is known before a GPU times it. The walk launches 4
warps, the chunked vote as many as `backends.TRITON_VOTE_KERNELS` names. "blocks per SM" takes
an sm_90 SM's limits (65,536 registers, 2,048 threads, 32 blocks, 228 KB shared memory;
registers allocated per warp in units of 256). --quick: the 3DGS count vote of the walk and
chunk16, and both kinds' projection and the emission of `triton_prepare` (what the tests run).
--labels: the vote's labels (its histogram's columns; the chunked vote holds a tile's one-hot
block of them in shared memory, so past `backends.CHUNKED_MAX_LABELS` no block fits an SM).
--kernels: only these (walk, chunk16, chunk32, chunk16w16, prepare).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from pathlib import Path

import pandas as pd

from sagonline.core.files import atomic_write_text

# Compile, never interpret: set before triton is first imported (render.triton_vote would
# choose the interpreter on a machine without CUDA).
os.environ["TRITON_INTERPRET"] = "0"

# sm_90's limits per SM
REGISTERS, THREADS, BLOCKS, SHARED = 65_536, 2_048, 32, 228 * 1024

POINTER_TYPES = {  # the kernels' pointer arguments, as the vote passes them
    "params_ptr": "*fp32",
    "order_ptr": "*i64",
    "offsets_ptr": "*i64",
    "counts_ptr": "*i64",
    "ids_ptr": "*i64",
    "pixel_labels_ptr": "*i32",
    "rows_ptr": "*fp32",
    "out_ptr": "*fp64",
    "best_ptr": "*i64",
    "depth_ptr": "*fp32",
    "trans_ptr": "*fp32",
    "cast_ptr": "*i64",
    # triton_prepare's projection and emission
    "means_ptr": "*fp32",
    "quats_ptr": "*fp32",
    "scales_ptr": "*fp32",
    "opac_ptr": "*fp32",
    "cam_ptr": "*fp32",
    "boxes_ptr": "*fp32",
    "rects_ptr": "*i32",
    "valid_ptr": "*i8",
    "starts_ptr": "*i64",
    "depths_ptr": "*fp32",
    "keys_ptr": "*i64",
    "splats_ptr": "*i64",
}
SCALAR_TYPES = {"eps": "fp32", "delta": "fp32", "t_stop": "fp32", "near": "fp32"}  # else i32


def compile_for(fn, constants: dict, warps: int, arch: int):
    """`fn` (a triton.jit kernel) compiled for CUDA sm_`arch` with `constants` bound."""
    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    names = list(fn.arg_names)
    signature = {
        name: "constexpr"
        if name in constants
        else POINTER_TYPES.get(name, SCALAR_TYPES.get(name, "i32"))
        for name in names
    }
    bound = {(i,): constants[name] for i, name in enumerate(names) if name in constants}
    source = ASTSource(fn=fn, signature=signature, constexprs=bound)
    return triton.compile(source, target=GPUTarget("cuda", arch, 32), options={"num_warps": warps})


def resources(kernel) -> dict:
    """Registers per thread, its stack frame (registers spilled there) and the shared memory of
    a compiled kernel, read from its cubin by the cuobjdump in Triton's wheel."""
    import triton

    tool = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    with tempfile.NamedTemporaryFile(suffix=".cubin") as cubin:
        cubin.write(kernel.asm["cubin"])
        cubin.flush()
        text = subprocess.run(
            [str(tool), "--dump-resource-usage", cubin.name],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    line = next(line for line in text.splitlines() if "REG:" in line)
    fields = dict(item.split(":", 1) for item in line.split() if ":" in item)
    return {
        "registers": int(fields["REG"]),
        "stack_bytes": int(fields["STACK"]),  # a thread's stack frame: its spilled registers
        "shared_bytes": int(fields["SHARED"]) + kernel.metadata.shared,  # static + launch's
    }


def blocks_per_sm(registers: int, shared: int, warps: int) -> int:
    """Thread blocks of `warps` warps an sm_90 SM holds at once."""
    per_warp = -(-registers * 32 // 256) * 256  # allocated per warp in units of 256
    by_registers = REGISTERS // (per_warp * warps)
    by_shared = SHARED // shared if shared else BLOCKS
    return min(by_registers, by_shared, THREADS // (32 * warps), BLOCKS)


def variants(quick: bool, labels: int = 3):
    """(kernel, variant, function, constants, warps) of each vote kernel and rule form over
    `labels` labels (padded as the launches pad them), then of `triton_prepare`'s projection
    (per kind) and emission."""
    import triton

    from sagonline.render import triton_prepare as prepare
    from sagonline.render.backends import TRITON_VOTE_KERNELS
    from sagonline.render.triton_vote import CHECK_EVERY, TILE, _walk_kernel
    from sagonline.render.triton_vote_chunk import _vote_chunk_kernel

    kinds = [("3dgs", False)] if quick else [("3dgs", False), ("2dgs", True)]
    weightings = [("count", False)] if quick else [("count", False), ("blend", True)]
    for kind, surfel in kinds:
        for weighting, weighted in weightings:
            rule = {"SURFEL": surfel, "WEIGHTED": weighted, "USE_DISTANCE": not weighted}
            shape = {"TILE": TILE, "NP": 13 if surfel else 7}
            padded = triton.next_power_of_2(labels)
            walk = {"COMPOSITE": False, "IMAGE": False, "KP": max(2, padded)}
            walk["CHECK_EVERY"] = CHECK_EVERY
            yield "walk", f"{kind} {weighting}", _walk_kernel, rule | shape | walk, 4
            for name, (chunk, warps) in TRITON_VOTE_KERNELS.items():
                if chunk and (name == "chunk16" or not quick):
                    chunked = rule | shape | {"KP": max(16, padded), "CHUNK": chunk}
                    yield name, f"{kind} {weighting}", _vote_chunk_kernel, chunked, warps
    for kind, surfel in [("3dgs", False), ("2dgs", True)]:  # both kinds' branches, --quick too
        shape = {"SURFEL": surfel, "NP": 13 if surfel else 7, "TILE": TILE}
        block = {"BLOCK": prepare.PROJECT_BLOCK}
        yield "prepare: project", kind, prepare._project_kernel, shape | block, 4
    emit = {"SPLATS": prepare.EMIT_SPLATS, "TILES": prepare.EMIT_TILES}
    yield "prepare: emit", "both kinds", prepare._emit_kernel, emit, 4


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", type=int, default=90, help="CUDA compute capability, e.g. 90")
    ap.add_argument("--out", type=Path, default=None, help="also write the table as a CSV")
    ap.add_argument("--labels", type=int, default=3, help="the vote's labels (default 3)")
    ap.add_argument("--kernels", default=None, help="only these, comma-separated (default all)")
    ap.add_argument("--quick", action="store_true", help="the 3DGS count vote only")
    args = ap.parse_args()
    if args.labels < 1:
        ap.error("--labels: at least 1")
    from sagonline.render.backends import TRITON_VOTE_KERNELS

    known = (*TRITON_VOTE_KERNELS, "prepare")
    chosen = known if args.kernels is None else tuple(args.kernels.split(","))
    if not chosen or set(chosen) - set(known):
        ap.error(f"--kernels {args.kernels}: name some of {', '.join(known)}")
    rows = []
    for kernel, variant, fn, constants, warps in variants(args.quick, args.labels):
        if kernel.split(":")[0] not in chosen:  # "prepare: project" is of prepare
            continue
        used = resources(compile_for(fn, constants, warps, args.arch))
        rows.append(
            {"kernel": kernel, "variant": variant, "warps": warps}
            | used
            | {"blocks_per_sm": blocks_per_sm(used["registers"], used["shared_bytes"], warps)}
        )
    table = pd.DataFrame(rows)
    table["occupancy %"] = (100 * table.blocks_per_sm * 32 * table.warps / THREADS).round(1)
    print(
        f"Triton vote kernels compiled for sm_{args.arch}, {args.labels} labels (no GPU needed)\n"
    )
    print(table.to_markdown(index=False))
    if args.out is not None:
        atomic_write_text(args.out, table.assign(arch=args.arch).to_csv(index=False))


if __name__ == "__main__":
    main()
