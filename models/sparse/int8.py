"""The int8 sparse kernels: the C++ extension `csrc/sparse_conv_int8.cpp`, built and loaded as the float kernels are.

Unsigned 8-bit activation rows times signed 8-bit weights, accumulated exactly in int32 over a kernel map's
neighbour table, with the float kernels' fused epilogue (a per-output-channel scale, bias, residual, ReLU) and the
result written as float32 or requantised to uint8. On a CPU with AVX-512 VNNI the micro-kernels use `vpdpbusd`
(16 lanes), with AVX-VNNI and no AVX-512 the same instruction on 8 lanes (built, not run on our machines: none has
it), elsewhere AVX2's `vpmaddwd` on operands widened to int16 (exact: no int16 saturation as `vpmaddubsw` would
have). `path()` says which one this build runs.

A separate extension from the float one (`models.sparse.compiled`), cached beside it under the same rules: a folder
named by a hash of the source, the flags, torch's and Python's versions and the CPU's instruction-set flags
(`-march=native`). `build("avx2")` builds the AVX2 variant on an AVX-512 machine (the tests compare both).
"""

from __future__ import annotations

import hashlib
import logging
import platform
import sys
import threading
import time
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from models.sparse import compiled

logger = logging.getLogger(__name__)

SOURCE = Path(__file__).parent / "csrc" / "sparse_conv_int8.cpp"
INSTRUCTION_SETS = {"native": (), "avx2": ("-mno-avx512f",)}
"""`native`: everything this CPU has (VNNI where present); `avx2`: AVX-512 (and with it VNNI) off."""

_module: ModuleType | None = None
_lock = threading.Lock()


def build_key(instruction_set: str = "native") -> str:
    """Hash of everything the compiled code depends on."""
    digest = hashlib.sha256()
    flags = compiled.CFLAGS + INSTRUCTION_SETS[instruction_set] + compiled.LDFLAGS
    for part in (SOURCE.read_bytes(), " ".join(flags).encode(), torch.__version__.encode(), sys.version.encode(),
                 compiled.cpu_flags().encode(), platform.machine().encode()):
        digest.update(part)
        digest.update(b"\0")
    return digest.hexdigest()[:16]


def build(instruction_set: str = "native") -> ModuleType:
    """The int8 kernels compiled for `instruction_set` (a key of `INSTRUCTION_SETS`), cached.

    Raises:
        RuntimeError: the build failed; the message says why.
    """
    from torch.utils import cpp_extension  # noqa: PLC0415  (imports setuptools: only when needed)

    if instruction_set not in INSTRUCTION_SETS:
        raise ValueError(f"instruction set must be one of {tuple(INSTRUCTION_SETS)}, got {instruction_set!r}")
    name = f"radarseg_sparse_int8_{build_key(instruction_set)}"
    directory = compiled.build_root() / name
    cached = (directory / f"{name}.so").is_file()
    if not cached:
        logger.info("building the int8 sparse kernels (%s) in %s", instruction_set, directory)
    started = time.perf_counter()
    try:
        compiled._ensure_ninja_on_path()
        directory.mkdir(parents=True, exist_ok=True)
        with compiled._build_lock(directory):
            module = cpp_extension.load(
                name=name, sources=[str(SOURCE)], build_directory=str(directory),
                extra_cflags=list(compiled.CFLAGS + INSTRUCTION_SETS[instruction_set]),
                extra_ldflags=list(compiled.LDFLAGS), verbose=False)
    except Exception as error:  # noqa: BLE001  (compiler, ninja, linker or file errors all mean "no kernels")
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise RuntimeError(f"the int8 sparse kernels did not build ({type(error).__name__}: {first_line})") \
            from error
    if not cached:
        logger.info("built the int8 sparse kernels in %.1f s", time.perf_counter() - started)
    return module


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
