"""Kernel maps of the exported segmenter graph (``segmenter.onnx``), in numpy alone.

This file imports nothing but numpy, so a deployment can copy it (or load it by path) and feed the ONNX
graph without torch or this package. It computes, for the voxels of one frame, the integer inputs of the
graph: which voxel each sparse convolution reads. The float input is the voxels' features (N, 4).

Voxels at tensor stride ``s`` (s = 1, 2, 4, 8, 16) are the input voxels at ``s = 1`` (in the caller's
order) and ``unique(floor(coords / s))`` (sorted lexicographically) above. Per stride the graph takes:

- the 3^3 submanifold convolutions' neighbours, as z-columns (export format 4): the voxel at ``q + d`` for every
  voxel ``q`` and offset ``d`` in ``{-1, 0, 1}^3`` (x outermost, z innermost) is entry ``d_z`` of the column at
  ``q + (d_x, d_y, 0)``, so the graph gathers each column's three rows once and then 9 columns per voxel, about
  half the row copies of 27 single rows (a `small` ROI has 1.3 columns per voxel):

  - ``columns_s{s}`` (M_s, 3) int64: rows of the voxels at ``p - z``, ``p``, ``p + z`` of each column ``p``,
    ``N_s`` where there is none (the graph appends a zero row to the features, so a missing neighbour
    multiplies zeros). Row ``j < N_s`` is voxel ``j``'s own column; the rows after them are the empty
    positions next to a voxel in x / y that have one at z - 1 or z + 1, and the last row is an empty column
    (``N_s`` three times);
  - ``neighbours_s{s}`` (N_s, 9) int64: the ``columns_s{s}`` row of ``q + (d_x, d_y, 0)`` for every voxel ``q``
    and ``(d_x, d_y)`` in ``{-1, 0, 1}^2`` (x outer), ``M_s - 1`` (the empty column) where there is no voxel in
    it. :func:`expand_neighbours` gives the (N_s, 27) table back;
- ``down_s{s}`` (N_2s, 8) int64 for s < 16: row at stride ``s`` of the voxel ``2 q + d`` for every
  coarse voxel ``q`` and ``d`` in ``{0, 1}^3``, ``N_s`` where there is none: the 2^3 stride-2 convolutions;
- ``up_s{s}`` (N_s,) int64 for s < 16: ``8 * parent_row + k`` for every voxel at stride ``s``, its
  parent at stride ``2s`` and ``k`` the index of its corner in ``{0, 1}^3``: the transposed convolutions.

These are exactly the maps ``models.sparse`` builds (``VoxelIndex.neighbour_table``, ``KernelMap.parent_slots``;
the 3^3 tables through :func:`expand_neighbours`); a test in this package checks that they agree.
"""

from __future__ import annotations

import itertools

import numpy as np

STRIDES = (1, 2, 4, 8, 16)
"""Tensor strides of the MinkUNet: the stem and four encoder stages."""
SUBMANIFOLD_OFFSETS = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)  # (27, 3)
DOWN_OFFSETS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int64)  # (8, 3)


def input_names() -> list[str]:
    """Names of the integer graph inputs, in the graph's order (after ``features``)."""
    names = [f"columns_s{s}" for s in STRIDES]
    names += [f"neighbours_s{s}" for s in STRIDES]
    names += [f"down_s{s}" for s in STRIDES[:-1]]
    names += [f"up_s{s}" for s in STRIDES[:-1]]
    return names


class _Grid:
    """Dense grid over the padded bounding box of a voxel set, holding each voxel's row (N where empty).

    int32 cells (a frame's voxels are far below 2^31): half the memory to fill, and numpy gathers from an int32 array
    about 4x faster than from an int64 one (measured: 1.0 against 4.4-5.3 ms for a `small` ROI's 3^3 table);
    the rows come back as int64, the graph's index type."""

    def __init__(self, coords: np.ndarray, pad: int) -> None:
        self.num_voxels = len(coords)
        self.low = coords.min(axis=0) - pad
        dims = coords.max(axis=0) - self.low + 1 + pad
        self.steps = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
        self.grid = np.full(int(np.prod(dims)), self.num_voxels, dtype=np.int32)
        self.grid[self.flat(coords)] = np.arange(self.num_voxels, dtype=np.int32)

    def flat(self, coords: np.ndarray) -> np.ndarray:
        return (coords - self.low) @ self.steps

    def rows(self, base: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """(M, K) rows of the voxels at ``base[j] + offsets[k]`` (inside the padded box by construction)."""
        return np.take(self.grid, self.flat(base)[:, None] + (offsets @ self.steps)[None, :]).astype(np.int64)


def stride_coords(coords: np.ndarray) -> dict[int, np.ndarray]:
    """Voxel coordinates (N_s, 3) at every stride of ``STRIDES`` (see the module docstring)."""
    levels = {1: coords}
    for finer, coarser in zip(STRIDES[:-1], STRIDES[1:], strict=True):
        # unique rows through an occupancy grid of the coarse box: O(cells), already in lexicographic order
        halves = levels[finer] // 2
        dims = halves.max(axis=0) + 1
        occupied = np.zeros(tuple(int(v) for v in dims), dtype=bool)
        occupied[tuple(halves.T)] = True
        levels[coarser] = np.stack(np.nonzero(occupied), axis=1).astype(np.int64)
    return levels


def column_tables(neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 3^3 neighbour table (N, 27) (``N`` = missing) as z-columns: (``columns`` (M, 3), ``table`` (N, 9)), see
    the module docstring. An empty position is named by the voxel below it (key ``2 row``) or, without one, above
    it (``2 row + 1``): the same key whichever voxel reads it, so the columns are deduplicated in O(N) (a `small`
    ROI of 22 k voxels: 2.2 ms at stride 1, one thread)."""
    n = len(neighbours)
    table = np.ascontiguousarray(neighbours[:, 1::3])  # (n, 9) the column centres: a voxel's own column row
    flat_table = table.reshape(-1)
    hole = np.flatnonzero(flat_table == n)  # columns whose centre is empty
    triples = neighbours.reshape(-1, 3)
    below, above = triples[hole, 0], triples[hole, 2]
    nothing = 2 * n + 1  # the key of a column with no voxel at all
    key = np.where(below != n, 2 * below, 2 * above + 1)
    marked = np.zeros(2 * n + 2, dtype=bool)
    marked[key] = True
    marked[nothing] = False
    keys = np.flatnonzero(marked)
    slot = np.cumsum(marked) - 1  # key -> its index among the empty positions
    ends = np.empty((2 * n + 2, 2), dtype=np.int64)
    ends[key, 0], ends[key, 1] = below, above  # the same pair for every reader of a key
    extras = np.stack([ends[keys, 0], np.full(len(keys), n, dtype=np.int64), ends[keys, 1]], axis=1)
    columns = np.concatenate([neighbours[:, 12:15], extras, np.full((1, 3), n, dtype=np.int64)])
    flat_table[hole] = np.where(key == nothing, len(columns) - 1, n + slot[key])
    return columns, table


def expand_neighbours(columns: np.ndarray, table: np.ndarray) -> np.ndarray:
    """The (N, 27) 3^3 neighbour table from its z-columns (:func:`column_tables`)."""
    return columns[table].reshape(len(table), 27)


def kernel_maps(coords: np.ndarray) -> dict[str, np.ndarray]:
    """The graph's integer inputs for one frame's voxels.

    Args:
        coords: (N, 3) integer voxel coordinates (range, angle, Doppler bins), N >= 1, unique rows,
            every value >= 0.

    Returns:
        ``{name: array}`` for every name of ``input_names()`` (shapes in the module docstring).

    Raises:
        ValueError: wrong shape, no voxel, a negative coordinate or a repeated row.
    """
    coords = np.asarray(coords)
    if coords.ndim != 2 or coords.shape[1] != 3 or not np.issubdtype(coords.dtype, np.integer):
        raise ValueError(f"coords must be (N, 3) integers, got {coords.shape} {coords.dtype}")
    if len(coords) == 0:
        raise ValueError("coords must hold at least one voxel")
    if coords.min() < 0:
        raise ValueError(f"coords must be >= 0 (bins), got a minimum of {coords.min()}")
    coords = coords.astype(np.int64, copy=False)
    levels = stride_coords(coords)
    grids = {s: _Grid(levels[s], pad=1) for s in STRIDES}
    if np.count_nonzero(grids[1].grid != len(coords)) != len(coords):  # a repeat overwrote a cell
        raise ValueError("coords contain repeated rows (a voxel is given once)")
    maps: dict[str, np.ndarray] = {}
    for s in STRIDES:
        maps[f"columns_s{s}"], maps[f"neighbours_s{s}"] = column_tables(grids[s].rows(levels[s], SUBMANIFOLD_OFFSETS))
    for finer, coarser in zip(STRIDES[:-1], STRIDES[1:], strict=True):
        maps[f"down_s{finer}"] = grids[finer].rows(2 * levels[coarser], DOWN_OFFSETS)
        fine = levels[finer]
        parent = np.take(grids[coarser].grid, grids[coarser].flat(fine // 2)).astype(np.int64)
        corner = (fine % 2) @ np.array([4, 2, 1], dtype=np.int64)
        maps[f"up_s{finer}"] = parent * 8 + corner
    return {name: maps[name] for name in input_names()}  # the graph's order


def segmenter_macs(maps: dict[str, np.ndarray], layers: list[dict]) -> tuple[int, int]:
    """Useful and executed multiply-accumulates of one run of the segmenter graph.

    Args:
        maps: this frame's ``kernel_maps``.
        layers: the manifest's ``segmenter.layers`` (kind, map, stride, in/out channels, kernel volume).

    Returns:
        (useful, executed): useful counts input/output voxel pairs x C_in x C_out (what the sparse
        convolution needs); executed adds the zeros the gathers multiply for missing neighbours and the
        products a transposed conv computes for absent children.
    """
    voxels = {s: len(maps[f"neighbours_s{s}"]) for s in STRIDES}
    pairs: dict[str, int] = {}  # present pairs per map, counted once: a frame's layers share 9 maps
    useful = executed = 0
    for layer in layers:
        stride, channels = layer["stride"], layer["in_channels"] * layer["out_channels"]
        if layer["kind"] == "gather":
            name = layer["map"]
            if name not in pairs:
                pairs[name] = _present_pairs(maps, name, voxels, stride)
            useful += pairs[name] * channels
            executed += len(maps[name]) * layer["kernel_volume"] * channels
        elif layer["kind"] == "pick":
            useful += voxels[stride] * channels
            executed += voxels[2 * stride] * layer["kernel_volume"] * channels
        else:
            useful += voxels[stride] * channels
            executed += voxels[stride] * channels
    return useful, executed


def _present_pairs(maps: dict[str, np.ndarray], name: str, voxels: dict[int, int], stride: int) -> int:
    """Input/output voxel pairs of a map: entries that name a voxel (a 3^3 map through its columns)."""
    if name.startswith("down"):
        return int(np.count_nonzero(maps[name] != voxels[stride // 2]))
    columns = maps[f"columns_s{stride}"]
    per_column = np.count_nonzero(columns != voxels[stride], axis=1)
    return int(per_column[maps[name]].sum())
