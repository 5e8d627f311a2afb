"""Kernel maps of the exported segmenter graph (``segmenter.onnx``), in numpy alone.

This file imports nothing but numpy, so a deployment can copy it (or load it by path) and feed the ONNX
graph without torch or this package. It computes, for the voxels of one frame, the integer inputs of the
graph: which voxel each sparse convolution reads. The float input is the voxels' features (N, 4).

Voxels at tensor stride ``s`` (s = 1, 2, 4, 8, 16) are the input voxels at ``s = 1`` (in the caller's
order) and ``unique(floor(coords / s))`` (sorted lexicographically) above. Per stride the graph takes:

- ``neighbours_s{s}`` (N_s, 27) int64: row of the voxel at ``q + d`` for every voxel ``q`` and offset
  ``d`` in ``{-1, 0, 1}^3`` (x outermost, z innermost), ``N_s`` where there is none (the graph appends a
  zero row to the features, so a missing neighbour multiplies zeros): the 3^3 submanifold convolutions;
- ``down_s{s}`` (N_2s, 8) int64 for s < 16: row at stride ``s`` of the voxel ``2 q + d`` for every
  coarse voxel ``q`` and ``d`` in ``{0, 1}^3``, ``N_s`` where there is none: the 2^3 stride-2 convolutions;
- ``up_s{s}`` (N_s,) int64 for s < 16: ``8 * parent_row + k`` for every voxel at stride ``s``, its
  parent at stride ``2s`` and ``k`` the index of its corner in ``{0, 1}^3``: the transposed convolutions.

These are exactly the maps ``models.sparse`` builds (``VoxelIndex.neighbour_table``, ``KernelMap.parent_slots``);
a test in this package checks that they agree.
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
    names = [f"neighbours_s{s}" for s in STRIDES]
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
        maps[f"neighbours_s{s}"] = grids[s].rows(levels[s], SUBMANIFOLD_OFFSETS)
    for finer, coarser in zip(STRIDES[:-1], STRIDES[1:], strict=True):
        maps[f"down_s{finer}"] = grids[finer].rows(2 * levels[coarser], DOWN_OFFSETS)
        fine = levels[finer]
        parent = np.take(grids[coarser].grid, grids[coarser].flat(fine // 2)).astype(np.int64)
        corner = (fine % 2) @ np.array([4, 2, 1], dtype=np.int64)
        maps[f"up_s{finer}"] = parent * 8 + corner
    return maps


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
            table = maps[layer["map"]]
            if layer["map"] not in pairs:
                num_in = voxels[stride // 2] if layer["map"].startswith("down") else voxels[stride]
                pairs[layer["map"]] = int(np.count_nonzero(table != num_in))
            useful += pairs[layer["map"]] * channels
            executed += table.size * channels
        elif layer["kind"] == "pick":
            useful += voxels[stride] * channels
            executed += voxels[2 * stride] * layer["kernel_volume"] * channels
        else:
            useful += voxels[stride] * channels
            executed += voxels[stride] * channels
    return useful, executed
