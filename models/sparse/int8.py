"""The int8 sparse kernels: the C++ extension `csrc/sparse_conv_int8.cpp`, built and loaded as the float kernels are.

Unsigned 8-bit activation rows times signed 8-bit weights, accumulated exactly in int32 over a kernel map's
neighbour table, with the float kernels' fused epilogue (a per-output-channel scale, bias, residual, ReLU) and the
result written as float32 or requantised to uint8. On a CPU with AVX-512 VNNI the micro-kernels use `vpdpbusd`
(16 lanes), with AVX-VNNI and no AVX-512 the same instruction on 8 lanes (built, not run on our machines: none has
it), elsewhere AVX2's `vpmaddwd` on operands widened to int16 (exact: no int16 saturation as `vpmaddubsw` would
have). `path()` says which one this build runs.

A separate extension from the float one (`models.sparse.compiled`, whose micro-kernel `csrc/micro_kernel.h` it
shares), built and cached by the same function: a folder named by a hash of the source and headers, the flags,
torch's and Python's versions and the CPU's instruction-set flags (`-march=native`). `build("avx2")` builds the
AVX2 variant on an AVX-512 machine (the tests compare both).
"""

from __future__ import annotations

import threading
from pathlib import Path
from types import ModuleType

from torch import Tensor

from models.sparse import compiled

SOURCE = Path(__file__).parent / "csrc" / "sparse_conv_int8.cpp"

_module: ModuleType | None = None
_lock = threading.Lock()


def build(instruction_set: str = "native") -> ModuleType:
    """The int8 kernels compiled for `instruction_set` (a key of `compiled.INSTRUCTION_SETS`: `native`, everything
    this CPU has, VNNI where present; `avx2`, AVX-512 and with it VNNI off), cached.

    Raises:
        ValueError: an unknown instruction set.
        RuntimeError: the build failed; the message says why.
    """
    return compiled.build_extension("radarseg_sparse_int8", (SOURCE,), instruction_set, "the int8 sparse kernels")


def load() -> ModuleType:
    """This CPU's int8 kernels (built on first use).

    Raises:
        RuntimeError: the build failed.
    """
    global _module
    if _module is None:
        with _lock:
            if _module is None:
                _module = build("native")
    return _module


def path() -> str:
    """Which micro-kernels this CPU's build runs: `avx512-vnni`, `avx2` or `scalar`."""
    return str(load().path)


def pack_weight(weight: Tensor, module: ModuleType | None = None) -> Tensor:
    """(K, C, D) int8 weight (C a multiple of 4) in the packed layout of `module` (default: this CPU's build)."""
    return (module or load()).pack_weight(weight.contiguous())


def neighbour_conv(src: Tensor, neighbours: Tensor, packed: Tensor, scale: Tensor, *, zero_point: int = 0,
                   weight_sums: Tensor | None = None, bias: Tensor | None = None, residual: Tensor | None = None,
                   residual_scale: Tensor | None = None, relu: bool = False, out_scale: Tensor | None = None
                   ) -> Tensor:
    """`epilogue(sum_k (src[neighbours[j, k]] - zero_point) . weight[k])` for each row j of `neighbours`.

    Args:
        src: (N, C) uint8 rows; neighbours: (M, K) int64, N where missing; packed: `pack_weight`'s.
        scale: (D,) float32, the int32 sums' scale (input scale x weight scale of each output channel).
        zero_point, weight_sums: the inputs' zero point and, where it is not 0, each offset's weight sums (K, D) int32.
        bias: (D,); residual: (M, D) float32, or uint8 with its `residual_scale` (D,); relu.
        out_scale: (D,) float32 > 0: requantised to uint8 with each output channel's scale; None: float32 out.
    """
    return load().neighbour_conv_int8(src.contiguous(), neighbours.contiguous(), packed, zero_point, weight_sums,
                                      scale, bias, None if residual is None else residual.contiguous(),
                                      residual_scale, relu, out_scale)


def compact_pairs(neighbours: Tensor, num_in: int) -> tuple[Tensor, Tensor, Tensor]:
    """A neighbour table (M, K) as the gather kernels visit it: per block of output rows and offset, the rows with a
    neighbour there and that neighbour (offsets (blocks * K + 1,) int32, rows in block uint8, neighbours int32).
    A map serves about ten convolutions at a level: built once, the kernels skip missing slots without looking."""
    offsets, rows, nbrs = load().compact_pairs(neighbours.contiguous(), num_in)
    return offsets, rows, nbrs


def neighbour_conv_pairs(src: Tensor, pairs: tuple[Tensor, Tensor, Tensor], shape: tuple[int, int], packed: Tensor,
                         scale: Tensor, *, zero_point: int = 0, weight_sums: Tensor | None = None,
                         bias: Tensor | None = None, residual: Tensor | None = None,
                         residual_scale: Tensor | None = None, relu: bool = False, out_scale: Tensor | None = None
                         ) -> Tensor:
    """:func:`neighbour_conv` over :func:`compact_pairs` of a table of ``shape`` (M, K): the same result."""
    residual = None if residual is None else residual.contiguous()
    return load().neighbour_conv_int8_pairs(src.contiguous(), *pairs, shape[0], shape[1], packed, zero_point,
                                            weight_sums, scale, bias, residual, residual_scale, relu, out_scale)


def scatter_conv(src: Tensor, neighbours: Tensor, packed: Tensor, num_out: int, scale: Tensor, *,
                 zero_point: int = 0, weight_sums: Tensor | None = None, bias: Tensor | None = None,
                 relu: bool = False, out_scale: Tensor | None = None) -> Tensor:
    """`out[neighbours[j, k]] = epilogue((src[j] - zero_point) . weight[k])` (each output row reached at most once;
    rows never reached: the epilogue of 0). Arguments as :func:`neighbour_conv`."""
    return load().scatter_conv_int8(src.contiguous(), neighbours.contiguous(), packed, num_out, zero_point,
                                    weight_sums, scale, bias, relu, out_scale)
