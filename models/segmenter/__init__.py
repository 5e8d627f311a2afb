"""Stage 2 of ERASE-Net: sparse segmenters labelling region-grown ROI voxels (docs/design.md section 7).

`MinkUNet` labels voxels of a `models.sparse.SparseTensor`; `SPVCNN` labels points of a `PointTensor`.
"""

from models.segmenter.minkunet import BASE_WIDTHS, MinkUNet, scaled_widths
from models.segmenter.spvcnn import SPVCNN, PointTensor, devoxelize, voxelize, voxelize_onto

__all__ = [
    "BASE_WIDTHS",
    "SPVCNN",
    "MinkUNet",
    "PointTensor",
    "devoxelize",
    "scaled_widths",
    "voxelize",
    "voxelize_onto",
]
