"""Kernel maps: which input voxel feeds which output voxel through which weight.

A map is a neighbour table (N_out, K): for each output voxel and kernel offset, the row of the input
voxel it reads, or N_in where there is none (so a zero row appended to the features serves every miss).
Rows are found in a `VoxelIndex`: a dense int32 grid over the padded bounding box of the input voxels
(per batch sample), holding each voxel's row, so all K neighbours of all outputs are one gather
(`grid[flat(q) + delta_k]`). When that box would be too large (`MAX_GRID_CELLS`), the index falls back
to hashing: a voxel's coordinate `(batch, x, y, z)` is packed into one int64 key (batch in the high
bits, each spatial coordinate biased into 16 bits) and looked up by binary search in the sorted keys.
On ROI-like voxel sets the grid builds a 3^3 map about 20x faster than the search.

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
from functools import cached_property

import torch
from torch import Tensor

from models.sparse import compiled

COORD_BITS = 16
"""Bits per spatial coordinate in a packed key."""
BATCH_BITS = 63 - 3 * COORD_BITS
"""Bits left for the batch index (15: up to 32,767 samples in one tensor)."""
COORD_BIAS = 1 << (COORD_BITS - 1)
MAX_ABS_COORD = COORD_BIAS - 4
"""Largest |spatial coordinate| accepted: the margin keeps `coordinate + offset` inside 16 bits."""
MAX_BATCH = (1 << BATCH_BITS) - 1
MAX_GRID_CELLS = 1 << 25
"""Largest dense index grid (cells over all batch samples: 128 MiB of int32); larger boxes use hashing."""
GRID_PAD = 1
"""Empty cells around the bounding box: enough for 3^3 submanifold and 2^3 down-sampling neighbours."""


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
    """Input/output voxel pairs per kernel offset, as a neighbour table and (on demand) per-offset lists.

    `neighbours[j, k]` is the input row output `j` reads through offset `k` (`num_in` where none).
    For offset `k`, output voxel `out_indices[k][j]` receives `in_features[in_indices[k][j]] @ W[k]`.
    The transposed convolution uses the same map with the roles of input and output swapped.

    Attributes:
        neighbours: (N_out, K) int64 input rows, `num_in` for a missing neighbour.
        pair_counts: (P_0, ..., P_{K-1}) as Python ints, for exact MAC counts without a device sync.
        identity_offset: index of the offset whose pairs are `(i, i)` for every voxel (the centre offset
            of a submanifold conv), so the conv multiplies without a gather or scatter; None otherwise.
        num_in: input voxel count.
        num_out: output voxel count.
        kernel_size: voxels per axis.
        stride: the conv stride the map was built for.
        out_order: (N_out,) int64 output rows sorted by coordinates (batch, x, y, z), or None when they
            already are (set on submanifold maps only): the compiled engine runs such a conv in that order
            (`in_coordinate_order`).
    """

    neighbours: Tensor
    pair_counts: tuple[int, ...]
    identity_offset: int | None
    num_in: int
    num_out: int
    kernel_size: int
    stride: int
    out_order: Tensor | None = None

    @property
    def num_pairs(self) -> int:
        """Total input/output pairs over all offsets (the MAC count is this times C_in x C_out)."""
        return sum(self.pair_counts)

    @property
    def num_offsets(self) -> int:
        """K, the kernel voxels."""
        return self.neighbours.shape[1]

    @cached_property
    def _pair_lists(self) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
        by_offset = self.neighbours.T  # (K, N_out)
        found = by_offset != self.num_in
        # nonzero() lists pairs grouped by offset, so one split recovers the per-offset lists.
        _, out_rows = found.nonzero(as_tuple=True)
        in_split = by_offset[found].split(self.pair_counts)
        return tuple(in_split), tuple(out_rows.split(self.pair_counts))

    @property
    def in_indices(self) -> tuple[Tensor, ...]:
        """One (P_k,) int64 tensor per offset: rows of the input features (built on first use)."""
        return self._pair_lists[0]

    @property
    def out_indices(self) -> tuple[Tensor, ...]:
        """One (P_k,) int64 tensor per offset: rows of the output features (built on first use)."""
        return self._pair_lists[1]

    @cached_property
    def in_coordinate_order(self) -> tuple[Tensor, Tensor | None]:
        """The neighbour table between rows in coordinate order, and that order (`out_order`), for the compiled
        engine: a submanifold conv whose rows are not sorted runs on features permuted into coordinate order,
        so that the rows one block of outputs gathers lie close together in memory (on randomly ordered voxels
        1.4-1.5x faster forward and backward, `benchmarks/sparse_conv.py`). `(neighbours, None)` where the
        rows are sorted already (region-grown ROIs are) or the map is not a submanifold one."""
        if self.out_order is None:
            return self.neighbours, None
        order = self.out_order
        rank = torch.empty(self.num_in + 1, dtype=torch.int64, device=self.neighbours.device)
        rank[order] = torch.arange(self.num_in, device=self.neighbours.device)
        rank[self.num_in] = self.num_in  # a missing neighbour stays missing
        return rank[self.neighbours.index_select(0, order)], order

    @cached_property
    def parent_slots(self) -> Tensor:
        """(N_in,) int64 `out_row * K + k` of the one pair each input voxel is in (a down-sampling map,
        where every fine voxel has exactly one coarse parent): the transposed conv's gather index."""
        found = self.neighbours != self.num_in  # (N_out, K)
        slots = found.reshape(-1).nonzero().squeeze(1)
        parent = torch.empty(self.num_in, dtype=torch.int64, device=self.neighbours.device)
        parent[self.neighbours.reshape(-1)[slots]] = slots
        return parent


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
    if keys.numel() > 1 and bool((keys[1:] > keys[:-1]).all()):  # in order and unique already (ROIs, coarse levels)
        return keys, torch.arange(keys.numel(), device=keys.device)
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


class VoxelIndex:
    """Row of every voxel of one voxel set, looked up by coordinates (see the module docstring).

    A dense grid when the padded bounding box over all batch samples has at most `max_cells` cells,
    sorted packed keys otherwise; both give the same answers.
    """

    def __init__(self, coords: Tensor, *, max_cells: int = MAX_GRID_CELLS, pad: int = GRID_PAD) -> None:
        """Index a voxel set.

        Args:
            coords: (N, 4) int64 `(batch, x, y, z)`, unique rows.
            max_cells: largest grid; 0 forces hashing.
            pad: empty cells kept around the box on every side.

        Raises:
            ValueError: duplicate coordinates.
        """
        self.coords = coords
        self.num_voxels = coords.shape[0]
        self.device = coords.device
        self.grid: Tensor | None = None
        self._sorted: tuple[Tensor, Tensor] | None = None
        if self.num_voxels == 0:
            self._sorted = sort_keys(coords)
            return
        low = coords.min(dim=0).values
        high = coords.max(dim=0).values
        self.low = low - torch.tensor([0, pad, pad, pad], device=self.device)  # (4,) batch, x, y, z origin
        dims = (high - self.low + 1 + torch.tensor([0, pad, pad, pad], device=self.device)).tolist()
        cells = dims[0] * dims[1] * dims[2] * dims[3]
        if cells > max_cells:
            self._sorted = sort_keys(coords)
            return
        self.dims = dims
        self.steps = torch.tensor([dims[1] * dims[2] * dims[3], dims[2] * dims[3], dims[3], 1], device=self.device)
        flat = self._flat(coords)
        grid = torch.full((cells,), self.num_voxels, dtype=torch.int32, device=self.device)
        rows = torch.arange(self.num_voxels, dtype=torch.int32, device=self.device)
        grid[flat] = rows
        if not bool((grid[flat] == rows).all()):  # a later duplicate overwrote an earlier row
            raise ValueError("sparse tensor coordinates contain duplicate (batch, x, y, z) rows")
        self.grid = grid

    def _flat(self, coords: Tensor) -> Tensor:
        return ((coords - self.low) * self.steps).sum(dim=-1)

    @property
    def uses_grid(self) -> bool:
        """True when lookups go through the dense grid."""
        return self.grid is not None

    def sorted_keys(self) -> tuple[Tensor, Tensor]:
        """Sorted packed keys (N,) and the row of each (`sort_keys`), built on first use."""
        if self._sorted is None:
            self._sorted = sort_keys(self.coords)
        return self._sorted

    def neighbour_table(self, out_coords: Tensor, offsets: Tensor, scale: int) -> Tensor:
        """Rows of the voxels at `scale * q + d` for every output `q` and offset `d`.

        Args:
            out_coords: (M, 4) int64 `(batch, x, y, z)`.
            offsets: (K, 3) int64.
            scale: spatial factor applied to `out_coords` (the conv stride).

        Returns:
            (M, K) int64 rows of this voxel set, `num_voxels` where the voxel is absent.
        """
        base = out_coords.clone()
        base[:, 1:] *= scale
        num_offsets = offsets.shape[0]
        if len(base) == 0 or self.num_voxels == 0:
            return torch.full((len(base), num_offsets), self.num_voxels, dtype=torch.int64, device=self.device)
        if self.grid is not None:
            position = base - self.low  # (M, 4) cells from the grid's origin
            reach_low = position.min(dim=0).values[1:] + offsets.min(dim=0).values
            reach_high = position.max(dim=0).values[1:] + offsets.max(dim=0).values
            batch_ok = int(position[:, 0].min()) >= 0 and int(position[:, 0].max()) < self.dims[0]
            inside = batch_ok and bool((reach_low >= 0).all()) and all(
                int(h) < d for h, d in zip(reach_high.tolist(), self.dims[1:], strict=True))
            if inside:
                delta = (offsets * self.steps[1:]).sum(dim=1)  # (K,)
                flat = (position * self.steps).sum(dim=1)  # (M,)
                if compiled.enabled_on(self.device):  # the compiled engine reads it in one pass
                    return compiled.grid_neighbours(self.grid, flat, delta)
                return self.grid[flat[:, None] + delta[None, :]].long()
        # Hashing: packing is additive while every biased field stays inside its 16 bits (guaranteed by
        # the coordinate range check), so key(b, s*q + d) = key(b, s*q) + key of the offset d alone.
        sorted_keys, perm = self.sorted_keys()
        field_scale = torch.tensor([1 << (2 * COORD_BITS), 1 << COORD_BITS, 1], dtype=torch.int64, device=self.device)
        offset_keys = (offsets * field_scale).sum(dim=1)  # (K,)
        base_keys = pack_keys(base[:, 0], base[:, 1:])
        rows, found = lookup(sorted_keys, perm, base_keys[:, None] + offset_keys[None, :])
        return torch.where(found, rows, self.num_voxels)


def build_kernel_map(
    index: VoxelIndex,
    out_coords: Tensor,
    kernel_size: int,
    stride: int,
    *,
    same_coords: bool,
) -> KernelMap:
    """Build the kernel map from input voxels to output voxels.

    Args:
        index: the input voxels' index.
        out_coords: (N_out, 4) int64 output coordinates `(batch, x, y, z)` at the output resolution.
        kernel_size: voxels per axis.
        stride: 1 for submanifold maps, `kernel_size` for down-sampling maps.
        same_coords: True when output coordinates are the input coordinates in the same order; the
            centre offset is then the identity map.

    Returns:
        The map; its tensors live on the device of `out_coords`.
    """
    offsets = kernel_offsets(kernel_size, stride, out_coords.device)  # (K, 3)
    neighbours = index.neighbour_table(out_coords, offsets, stride)  # (N_out, K)
    pair_counts = (neighbours != index.num_voxels).sum(dim=0).tolist()
    out_order = None
    if same_coords and index.num_voxels > 1:
        order = index.sorted_keys()[1]
        if not bool((order[1:] > order[:-1]).all()):  # sorted already (coarse strides are): keep None
            out_order = order
    return KernelMap(
        neighbours=neighbours,
        pair_counts=tuple(pair_counts),
        identity_offset=offsets.shape[0] // 2 if (same_coords and stride == 1) else None,
        num_in=index.num_voxels,
        num_out=out_coords.shape[0],
        kernel_size=kernel_size,
        stride=stride,
        out_order=out_order,
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
