"""Kernel maps by coordinate hashing: which input voxel feeds which output voxel through which weight.

A voxel's coordinate `(batch, x, y, z)` is packed into one int64 key (batch in the high bits, each
spatial coordinate biased into 16 bits), so finding a neighbour is a binary search in the sorted keys
of the input voxels. All kernel offsets are searched at once with one batched `torch.searchsorted`.

Offset conventions (they match `torch.nn.functional.conv3d` / `conv_transpose3d` on a dense grid whose
origin is coordinate 0, weight index `k` running over `itertools.product` of the per-axis offsets):

- stride 1, odd kernel `k` (submanifold): output `q` reads input `q + d`, `d` in `{-(k//2) .. k//2}^3`;
  the all-zero offset is the identity map when input and output coordinates are the same.
- stride `s` = kernel `k` (non-overlapping down-sampling): output `q` reads input `s*q + d`,
  `d` in `{0 .. k-1}^3`; output coordinates are `unique(floor(input / s))`.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import Tensor

COORD_BITS = 16
"""Bits per spatial coordinate in a packed key."""
BATCH_BITS = 63 - 3 * COORD_BITS
"""Bits left for the batch index (15: up to 32,767 samples in one tensor)."""
COORD_BIAS = 1 << (COORD_BITS - 1)
MAX_ABS_COORD = COORD_BIAS - 4
"""Largest |spatial coordinate| accepted: the margin keeps `coordinate + offset` inside 16 bits."""
MAX_BATCH = (1 << BATCH_BITS) - 1


def check_coords(coords: Tensor) -> None:
    """Reject coordinates that cannot be packed into a key.

    Args:
        coords: (N, 4) int64, `(batch, x, y, z)` in voxels.

    Raises:
        ValueError: wrong shape or dtype, a negative or too large batch index, or a spatial coordinate
            with absolute value above `MAX_ABS_COORD`.
    """
    if coords.ndim != 2 or coords.shape[1] != 4:
        raise ValueError(f"coordinates must have shape (N, 4) = (batch, x, y, z), got {tuple(coords.shape)}")
    if coords.dtype != torch.int64:
        raise ValueError(f"coordinates must be int64, got {coords.dtype}")
    if coords.shape[0] == 0:
        return
    batch_lo, batch_hi = int(coords[:, 0].min()), int(coords[:, 0].max())
    if batch_lo < 0 or batch_hi > MAX_BATCH:
        raise ValueError(f"batch index must lie in [0, {MAX_BATCH}], got [{batch_lo}, {batch_hi}]")
    spatial_abs = int(coords[:, 1:].abs().max())
    if spatial_abs > MAX_ABS_COORD:
        raise ValueError(f"spatial coordinates must satisfy |c| <= {MAX_ABS_COORD}, got |c| = {spatial_abs}")


def pack_keys(batch: Tensor, spatial: Tensor) -> Tensor:
    """Pack batch index and spatial coordinates into one int64 key per voxel.

    Keys order voxels by batch, then x, y, z; two voxels share a key only if all four values match.

    Args:
        batch: (...) int64 batch index.
        spatial: (..., 3) int64 spatial coordinates (within `MAX_ABS_COORD` plus a small offset).

    Returns:
        (...) int64 keys.
    """
    shifted = spatial + COORD_BIAS
    key = batch
    for axis in range(3):
        key = (key << COORD_BITS) | shifted[..., axis]
    return key


def kernel_offsets(kernel_size: int, stride: int, device: torch.device | str | None = None) -> Tensor:
    """Kernel offsets in weight order (see the module docstring).

    Args:
        kernel_size: voxels per axis of the kernel.
        stride: 1 (then `kernel_size` must be odd, offsets centred) or equal to `kernel_size`.

    Returns:
        (kernel_size**3, 3) int64 offsets in voxels.

    Raises:
        ValueError: a combination other than the two supported ones.
    """
    if kernel_size < 1 or stride < 1:
        raise ValueError(f"kernel_size and stride must be >= 1, got {kernel_size} and {stride}")
    if stride == 1:
        if kernel_size % 2 != 1:
            raise ValueError(f"a stride-1 (submanifold) kernel must have odd size, got {kernel_size}")
        axis = range(-(kernel_size // 2), kernel_size // 2 + 1)
    elif kernel_size == stride:
        axis = range(kernel_size)
    else:
        raise ValueError(
            f"strided kernels must have kernel_size == stride, got kernel_size {kernel_size}, stride {stride}"
        )
    return torch.tensor(list(itertools.product(axis, axis, axis)), dtype=torch.int64, device=device)


@dataclass(frozen=True, eq=False)
class KernelMap:
    """Input/output voxel pairs per kernel offset.

    For offset `k`, output voxel `out_indices[k][j]` receives `in_features[in_indices[k][j]] @ W[k]`.
    The transposed convolution uses the same map with the roles of the two index lists swapped.

    Attributes:
        in_indices: one (P_k,) int64 tensor per offset, rows of the input features.
        out_indices: one (P_k,) int64 tensor per offset, rows of the output features.
        pair_counts: (P_0, ..., P_{K-1}) as Python ints, for exact MAC counts without a device sync.
        identity_offset: index of the offset whose pairs are `(i, i)` for every voxel (the centre offset
            of a submanifold conv), so the conv multiplies without a gather or scatter; None otherwise.
        num_in: input voxel count.
        num_out: output voxel count.
        kernel_size: voxels per axis.
        stride: the conv stride the map was built for.
    """

    in_indices: tuple[Tensor, ...]
    out_indices: tuple[Tensor, ...]
    pair_counts: tuple[int, ...]
    identity_offset: int | None
    num_in: int
    num_out: int
    kernel_size: int
    stride: int

    @property
    def num_pairs(self) -> int:
        """Total input/output pairs over all offsets (the MAC count is this times C_in x C_out)."""
        return sum(self.pair_counts)


def sort_keys(coords: Tensor) -> tuple[Tensor, Tensor]:
    """Sorted keys of a voxel set and the permutation that sorts it.

    Args:
        coords: (N, 4) int64 `(batch, x, y, z)`, unique rows.

    Returns:
        keys (N,) int64 ascending and perm (N,) int64 with `keys[i] == key(coords[perm[i]])`.

    Raises:
        ValueError: duplicate coordinates (a sparse tensor holds each voxel once).
    """
    keys = pack_keys(coords[:, 0], coords[:, 1:])
    sorted_keys, perm = torch.sort(keys)
    if sorted_keys.numel() > 1 and bool((sorted_keys[1:] == sorted_keys[:-1]).any()):
        raise ValueError("sparse tensor coordinates contain duplicate (batch, x, y, z) rows")
    return sorted_keys, perm


def lookup(sorted_keys: Tensor, perm: Tensor, query_keys: Tensor) -> tuple[Tensor, Tensor]:
    """Find query keys among sorted keys with one `searchsorted`.

    Args:
        sorted_keys: (M,) int64 ascending keys of the reference voxels.
        perm: (M,) int64 reference row of each sorted key.
        query_keys: (...) int64 keys to find.

    Returns:
        rows (...) int64, the reference row of each query (meaningless where not found), and
        found (...) bool.
    """
    if sorted_keys.numel() == 0:
        return torch.zeros_like(query_keys), torch.zeros_like(query_keys, dtype=torch.bool)
    position = torch.searchsorted(sorted_keys, query_keys).clamp_(max=sorted_keys.numel() - 1)
    found = sorted_keys[position] == query_keys
    return perm[position], found


def build_kernel_map(
    in_sorted_keys: Tensor,
    in_perm: Tensor,
    out_coords: Tensor,
    kernel_size: int,
    stride: int,
    *,
    same_coords: bool,
) -> KernelMap:
    """Build the kernel map from input voxels to output voxels.

    Args:
        in_sorted_keys: (N_in,) int64 sorted input keys (from `sort_keys`).
        in_perm: (N_in,) int64 input row of each sorted key.
        out_coords: (N_out, 4) int64 output coordinates `(batch, x, y, z)` at the output resolution.
        kernel_size: voxels per axis.
        stride: 1 for submanifold maps, `kernel_size` for down-sampling maps.
        same_coords: True when output coordinates are the input coordinates in the same order; the
            centre offset then becomes the identity map and is not searched.

    Returns:
        The map; its index tensors live on the device of `out_coords`.
    """
    device = out_coords.device
    offsets = kernel_offsets(kernel_size, stride, device)  # (K, 3)
    num_offsets = offsets.shape[0]
    identity_offset = num_offsets // 2 if (same_coords and stride == 1) else None
    searched = torch.arange(num_offsets, device=device)
    if identity_offset is not None:
        searched = searched[searched != identity_offset]

    # Packing is additive while every biased field stays inside its 16 bits (guaranteed by the
    # coordinate range check), so key(b, stride*q + d) = key(b, stride*q) + key of the offset d alone.
    # Sorting the base keys makes every row of queries ascending, which keeps the search cache-friendly.
    base_keys, out_order = torch.sort(pack_keys(out_coords[:, 0], stride * out_coords[:, 1:]))
    field_scale = torch.tensor([1 << (2 * COORD_BITS), 1 << COORD_BITS, 1], dtype=torch.int64, device=device)
    offset_keys = (offsets[searched] * field_scale).sum(dim=1)  # (K',)
    # One batched search over all offsets: queries (K', N_out).
    in_rows, found = lookup(in_sorted_keys, in_perm, base_keys[None, :] + offset_keys[:, None])

    # nonzero() lists pairs grouped by offset, so one split recovers the per-offset lists.
    offset_slot, sorted_out = found.nonzero(as_tuple=True)
    counts = found.sum(dim=1).tolist()
    in_split = in_rows[offset_slot, sorted_out].split(counts)
    out_split = out_order[sorted_out].split(counts)

    num_out = out_coords.shape[0]
    in_indices: list[Tensor] = [torch.empty(0, dtype=torch.int64, device=out_coords.device)] * num_offsets
    out_indices = list(in_indices)
    pair_counts = [0] * num_offsets
    for slot, offset_index in enumerate(searched.tolist()):
        in_indices[offset_index] = in_split[slot]
        out_indices[offset_index] = out_split[slot]
        pair_counts[offset_index] = counts[slot]
    if identity_offset is not None:
        identity = torch.arange(num_out, device=out_coords.device)
        in_indices[identity_offset] = identity
        out_indices[identity_offset] = identity
        pair_counts[identity_offset] = num_out
    return KernelMap(
        in_indices=tuple(in_indices),
        out_indices=tuple(out_indices),
        pair_counts=tuple(pair_counts),
        identity_offset=identity_offset,
        num_in=in_sorted_keys.numel(),
        num_out=num_out,
        kernel_size=kernel_size,
        stride=stride,
    )


def downsample_coords(coords: Tensor, factor: int) -> Tensor:
    """Coarser voxel set: `unique(floor(spatial / factor))` per batch sample.

    Args:
        coords: (N, 4) int64 `(batch, x, y, z)`.
        factor: down-sampling factor per axis (>= 1).

    Returns:
        (M, 4) int64 unique coarse coordinates, sorted by key (batch first).
    """
    coarse_spatial = torch.div(coords[:, 1:], factor, rounding_mode="floor")
    keys = torch.unique(pack_keys(coords[:, 0], coarse_spatial))
    return unpack_keys(keys)


def unpack_keys(keys: Tensor) -> Tensor:
    """Inverse of `pack_keys`.

    Args:
        keys: (M,) int64.

    Returns:
        (M, 4) int64 `(batch, x, y, z)`.
    """
    mask = (1 << COORD_BITS) - 1
    z = (keys & mask) - COORD_BIAS
    y = ((keys >> COORD_BITS) & mask) - COORD_BIAS
    x = ((keys >> (2 * COORD_BITS)) & mask) - COORD_BIAS
    batch = keys >> (3 * COORD_BITS)
    return torch.stack([batch, x, y, z], dim=1)
