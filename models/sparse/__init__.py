"""Sparse convolution: sparse tensors, kernel maps (dense index grids or hashing), conv layers, and the engines
that run them (`compiled`: C++ kernels; `paths`: the pure-PyTorch reference and the choice between them).

No sparse-convolution library trains on CPU here (docs/design.md section 7), so the project owns this one.
"""

from models.sparse.conv import (
    BatchNorm,
    MACCounted,
    PointwiseConv,
    ReLU,
    StridedConv3d,
    SubmanifoldConv3d,
    TransposedConv3d,
    last_forward_executed_macs,
    last_forward_macs,
)
from models.sparse.kernel_map import KernelMap, VoxelIndex, build_kernel_map, downsample_coords, kernel_offsets
from models.sparse.paths import apply_kernel_map, choose_path
from models.sparse.tensor import KernelMapCache, SparseTensor, cat_features

__all__ = [
    "BatchNorm",
    "KernelMap",
    "KernelMapCache",
    "MACCounted",
    "PointwiseConv",
    "ReLU",
    "SparseTensor",
    "StridedConv3d",
    "SubmanifoldConv3d",
    "TransposedConv3d",
    "VoxelIndex",
    "apply_kernel_map",
    "build_kernel_map",
    "choose_path",
    "last_forward_executed_macs",
    "cat_features",
    "last_forward_macs",
    "downsample_coords",
    "kernel_offsets",
]
