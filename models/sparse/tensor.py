"""The sparse tensor: voxel coordinates with a batch index, their features, and a shared map cache.

Coordinates at tensor stride `s` are in units of `s` finest voxels: a voxel `c` at stride `s` covers
the finest voxels `s*c .. s*c + s - 1` along each axis. Tensors derived from the same input (through
convolutions, BatchNorm, activations, concatenation) share one `KernelMapCache`, so every kernel map
and every coarser coordinate set is built once per forward pass and reused by all layers, including
the transposed convolutions on the way back up.
"""

from __future__ import annotations

import torch
from torch import Tensor

from models.sparse import compiled
from models.sparse.kernel_map import (
    MAX_GRID_CELLS,
    KernelMap,
    VoxelIndex,
    build_kernel_map,
    check_coords,
    downsample_coords,
)


class KernelMapCache:
    """Coordinates per tensor stride, their voxel indexes, and kernel maps, shared by derived tensors.

    The finest coordinates are kept in the order the caller gave them (so outputs line up with the
    caller's voxels); coarser ones are sorted by key.
    """

    def __init__(self, coords: Tensor, stride: int) -> None:
        """Start a cache from the coordinates of one tensor.

        Args:
            coords: (N, 4) int64 `(batch, x, y, z)` at tensor stride `stride`.
            stride: tensor stride of `coords` (finest voxels per coordinate step).
        """
        self._coords: dict[int, Tensor] = {stride: coords}
        self._index: dict[int, VoxelIndex] = {}
        self._maps: dict[tuple[int, int, int], KernelMap] = {}

    def coords(self, stride: int) -> Tensor:
        """Coordinates at a tensor stride, down-sampling from the nearest finer stride if needed.

        Args:
            stride: tensor stride; must be a known stride times a power of two.

        Returns:
            (N_stride, 4) int64 coordinates.

        Raises:
            KeyError: no known finer stride to derive `stride` from.
        """
        if stride not in self._coords:
            finer = stride // 2
            if stride % 2 != 0 or finer < 1:
                raise KeyError(f"no coordinates at tensor stride {stride} (known: {sorted(self._coords)})")
            self._coords[stride] = downsample_coords(self.coords(finer), 2)
        return self._coords[stride]

    def index(self, stride: int) -> VoxelIndex:
        """The voxel index (dense grid, or hashing for huge boxes) of the coordinates at `stride`."""
        if stride not in self._index:
            self._index[stride] = VoxelIndex(self.coords(stride))
        return self._index[stride]

    def sorted_keys(self, stride: int) -> tuple[Tensor, Tensor]:
        """Sorted keys (N,) int64 and the row of each, for the coordinates at `stride`."""
        return self.index(stride).sorted_keys()

    def kernel_map(self, tensor_stride: int, kernel_size: int, stride: int) -> KernelMap:
        """The kernel map of a conv reading tensor stride `tensor_stride`, built once and then reused.

        Args:
            tensor_stride: stride of the conv's input (the finer side for a down/up-sampling pair).
            kernel_size: voxels per axis.
            stride: 1 (submanifold, output coords = input coords) or `kernel_size` (output at
                `tensor_stride * stride`). A transposed conv asks for the map of the strided conv it
                inverts, with `tensor_stride` = its own output stride.

        Returns:
            The cached map.
        """
        key = (tensor_stride, kernel_size, stride)
        if key not in self._maps:
            self._maps[key] = build_kernel_map(
                self.index(tensor_stride),
                self.coords(tensor_stride * stride),
                kernel_size,
                stride,
                same_coords=stride == 1,
            )
        return self._maps[key]

    def build_pyramid(self, stride: int, levels: int) -> bool:
        """Build the coordinates, 3^3 submanifold maps and 2^3 down-sampling maps of `levels` tensor strides
        (`stride`, 2 `stride`, ...) in one compiled pass (`compiled.pyramid_maps`), as a U-Net's forward asks for
        them; the maps equal those `kernel_map` builds one by one.

        Returns:
            True when built; False when the compiled engine does not run here, the coordinates at `stride` are not
            sorted (the one-by-one path handles any order), or a level is too large for its column index.
        """
        coords = self.coords(stride)
        if levels < 1 or len(coords) == 0 or not compiled.enabled_on(coords.device):
            return False
        built = compiled.pyramid_maps(coords, levels, MAX_GRID_CELLS)
        if built is None:
            return False
        for level in range(levels):
            level_coords, sub, sub_counts, down, down_counts = built[5 * level: 5 * level + 5]
            tensor_stride = stride << level
            self._coords.setdefault(tensor_stride, level_coords)
            self._maps.setdefault((tensor_stride, 3, 1), KernelMap(
                neighbours=sub, pair_counts=tuple(sub_counts.tolist()), identity_offset=13,
                num_in=len(level_coords), num_out=len(level_coords), kernel_size=3, stride=1))
            if level + 1 < levels:
                self._maps.setdefault((tensor_stride, 2, 2), KernelMap(
                    neighbours=down, pair_counts=tuple(down_counts.tolist()), identity_offset=None,
                    num_in=len(level_coords), num_out=len(down), kernel_size=2, stride=2))
        return True

    @property
    def num_maps(self) -> int:
        """How many kernel maps have been built (each is built once)."""
        return len(self._maps)


class SparseTensor:
    """Voxels with features: `coords` (N, 4) int64 `(batch, x, y, z)` and `feats` (N, C).

    Attributes:
        coords: (N, 4) int64; batch index first, then three spatial coordinates in units of `stride`
            finest voxels. Rows are unique.
        feats: (N, C) float features, row `i` belonging to `coords[i]`.
        stride: tensor stride (1 for the input resolution, 2, 4, ... after down-sampling).
        cache: kernel-map cache shared with every tensor derived from the same input coordinates.
    """

    def __init__(self, coords: Tensor, feats: Tensor, stride: int = 1, *, cache: KernelMapCache | None = None) -> None:
        """Wrap coordinates and features.

        Args:
            coords: (N, 4) int64 `(batch, x, y, z)`, unique rows, |x|, |y|, |z| <= 32764.
            feats: (N, C) features on the same device.
            stride: tensor stride of `coords`.
            cache: an existing cache whose coordinates at `stride` are `coords` (internal use by layers);
                None starts a new cache after validating `coords`.

        Raises:
            ValueError: bad shapes, dtype, coordinate range or a row-count mismatch.
        """
        if feats.ndim != 2 or feats.shape[0] != coords.shape[0]:
            raise ValueError(
                f"features must have shape (N, C) with N = {coords.shape[0]} coordinates, got {tuple(feats.shape)}"
            )
        if stride < 1:
            raise ValueError(f"tensor stride must be >= 1, got {stride}")
        if cache is None:
            check_coords(coords)
            cache = KernelMapCache(coords, stride)
        self.coords = coords
        self.feats = feats
        self.stride = stride
        self.cache = cache

    def __len__(self) -> int:
        return self.coords.shape[0]

    @property
    def num_channels(self) -> int:
        """C, the feature width."""
        return self.feats.shape[1]

    @property
    def device(self) -> torch.device:
        return self.feats.device

    def replace_feats(self, feats: Tensor) -> SparseTensor:
        """Same voxels (and cache), new features (N, C')."""
        return SparseTensor(self.coords, feats, self.stride, cache=self.cache)

    def __repr__(self) -> str:
        return f"SparseTensor(voxels={len(self)}, channels={self.num_channels}, stride={self.stride})"


def cat_features(tensors: list[SparseTensor]) -> SparseTensor:
    """Concatenate the features of tensors on the same voxels (a U-Net skip connection).

    Args:
        tensors: tensors sharing one cache and one tensor stride.

    Returns:
        A tensor on the same voxels with features (N, sum of C).

    Raises:
        ValueError: the tensors are not on the same voxels.
    """
    first = tensors[0]
    for other in tensors[1:]:
        if other.cache is not first.cache or other.stride != first.stride:
            raise ValueError(
                f"can only concatenate features on the same voxels; got strides {first.stride} and "
                f"{other.stride}{'' if other.cache is first.cache else ' from different inputs'}"
            )
    return first.replace_feats(torch.cat([t.feats for t in tensors], dim=1))
