"""How far two runtimes' ROI labels agree: the share of the voxels that either labels as an object where both give
the same class. The int8 exports and the int8 kernels are each checked against the float network with it."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def roi_label_agreement(reference: Sequence[np.ndarray], labels: Sequence[np.ndarray]) -> float:
    """Share of the voxels non-background in either where both label maps agree (1.0 when there are none)."""
    same = total = 0
    for ref, got in zip(reference, labels, strict=True):
        voxels = (ref > 0) | (got > 0)
        same += int(np.count_nonzero(ref[voxels] == got[voxels]))
        total += int(np.count_nonzero(voxels))
    return same / total if total else 1.0
