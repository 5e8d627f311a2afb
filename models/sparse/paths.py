"""How one sparse convolution runs over its kernel map: on the compiled engine where it applies, otherwise on one
of the pure-PyTorch paths (`PATHS`) chosen per layer by `choose_path` from the map's fill, stride and widths.

The rule and its thresholds were measured on the shipped MinkUNet's ROIs and on blobs with
`benchmarks/sparse_conv.py` (forward + backward, one thread); the constants below name what each one decides.
"""

from __future__ import annotations

from torch import Tensor

from models.sparse.functions import (
    _CompiledConv,
    _GatherMatmulScatter,
    _NeighbourGemm,
    _PickProducts,
    compiled_applies,
)
from models.sparse.kernel_map import KernelMap

PATHS = ("per_offset", "gemm")
"""How a conv runs over its map: gather / matmul / scatter per offset (`per_offset`, executes exactly the
useful MACs), or all offsets in one matrix product (`gemm`: `_NeighbourGemm`, or `_PickProducts` for a
transposed conv, which also multiplies the missing neighbours)."""


GEMM_MIN_FILL = 0.25
"""Smallest fill (pairs / (N_out x K)) at which the GEMM path runs: it executes 1 / fill times the useful
MACs. On uniformly scattered voxels (fill 0.08) the per-offset path wins."""
GEMM_MAX_IN_CHANNELS = 16
"""Widest input of a submanifold (K = 27) or transposed conv run by the GEMM path: above it the per-offset path
is as fast or faster on the shipped ROIs (wider thresholds, 24 and 32, gave training steps within 6 % at ratio
0.25 and slower ones at ratio 0.37)."""

GEMM_WIDE_MIN_FILL = 0.65
GEMM_WIDE_MIN_VOXELS = 16384
"""A submanifold map with at least this fill and this many outputs takes the GEMM path at any width: the
per-offset path's gathers and scatters no longer fit in cache, and the GEMM wastes under 1 / 0.65 - 1 = 54 %."""


def choose_path(kernel_map: KernelMap, in_channels: int, out_channels: int, *, transposed: bool) -> str:
    """`per_offset` or `gemm` for one conv, from the map's fill (pairs / (N_out x K)), stride and widths.

    The GEMM executes 1 / fill times the useful MACs but in one large product; the per-offset path executes only
    the useful ones but pays a gather, a product and a scatter per offset. Hence, measured on the shipped
    MinkUNet's ROIs (fill 0.45-0.85 at every stride; `benchmarks/sparse_conv.py`, forward + backward):

    - below `GEMM_MIN_FILL`, per offset (the waste dominates);
    - down-sampling (K = 8): GEMM at every width (0.3-0.7x the per-offset time: 8 offsets of about one product
      per input voxel each are mostly overhead);
    - submanifold (K = 27) and up-sampling (transposed, K = 8, whose GEMM multiplies all 8 children of a coarse
      voxel): GEMM up to `GEMM_MAX_IN_CHANNELS` input channels, per offset above, where wide gathered rows make
      the wasted MACs cost more than the per-offset overhead (0.45-0.8x at 8 channels; 0.8x per offset at 64);
    - except large, well-filled submanifold maps (at least `GEMM_WIDE_MIN_VOXELS` outputs and fill >=
      `GEMM_WIDE_MIN_FILL`), whose per-offset gathers and scatters no longer fit in cache: GEMM at every width
      (20 k blob voxels at fill 0.77: 0.74x at 32 channels, 0.79x at 64).
    """
    # The same fill for a transposed conv: it computes K products per coarse voxel and keeps num_pairs.
    fill = kernel_map.num_pairs / max(1, kernel_map.num_out * kernel_map.num_offsets)
    if fill < GEMM_MIN_FILL:
        return "per_offset"
    if kernel_map.stride == 1 and not transposed and fill >= GEMM_WIDE_MIN_FILL \
            and kernel_map.num_out >= GEMM_WIDE_MIN_VOXELS:
        return "gemm"
    if (kernel_map.stride == 1 or transposed) and in_channels > GEMM_MAX_IN_CHANNELS:
        return "per_offset"
    return "gemm"


def apply_kernel_map(feats: Tensor, weight: Tensor, kernel_map: KernelMap, *, transposed: bool,
                     path: str = "auto") -> tuple[Tensor, int, int]:
    """Run one sparse convolution over a kernel map.

    Args:
        feats: (N_in, C_in) input features (for `transposed`, the coarse side of the map).
        weight: (K, C_in, C_out).
        kernel_map: pairs per offset; `transposed` swaps its input and output roles.
        transposed: run the adjoint (up-sampling) of the map's convolution.
        path: one of `PATHS`, or "auto" for `choose_path`: how the pure-PyTorch engine runs it (the compiled
            engine, where `compiled_applies`, has one path and ignores this).

    Returns:
        output features (N_out, C_out), the useful MACs (pairs x C_in x C_out) and the executed MACs.
    """
    c_in, c_out = weight.shape[1], weight.shape[2]
    useful = kernel_map.num_pairs * c_in * c_out
    if compiled_applies(kernel_map, feats, weight):
        out = _CompiledConv.apply(feats, weight, kernel_map, transposed)
        return out, useful, useful
    if path == "auto":
        path = choose_path(kernel_map, c_in, c_out, transposed=transposed)
    if path == "gemm":
        if transposed:
            out = _PickProducts.apply(feats, weight, kernel_map)
            return out, useful, kernel_map.num_out * kernel_map.num_offsets * c_in * c_out
        out = _NeighbourGemm.apply(feats, weight, kernel_map)
        return out, useful, kernel_map.num_out * kernel_map.num_offsets * c_in * c_out
    if path != "per_offset":
        raise ValueError(f"path must be one of {PATHS} or 'auto', got {path!r}")
    if transposed:
        sources, targets, num_out = kernel_map.out_indices, kernel_map.in_indices, kernel_map.num_in
    else:
        sources, targets, num_out = kernel_map.in_indices, kernel_map.out_indices, kernel_map.num_out
    out = _GatherMatmulScatter.apply(
        feats, weight, sources, targets, kernel_map.pair_counts, kernel_map.identity_offset, num_out
    )
    return out, useful, useful
