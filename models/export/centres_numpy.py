"""Centres from the detector graph's outputs (``detector.onnx``), in numpy alone.

The same decoding as :meth:`models.detector.centernet.CentreNetHead.decode` (which the ONNX engine runs), for a
deployment without torch: local maxima of the heatmap over 3x3 cells, the ``k`` best, those scoring at least
``score_threshold``, placed at ``(cell + offset) * output_stride`` input bins.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


def decode_centres(heatmap: np.ndarray, offset: np.ndarray, doppler: np.ndarray, *, k: int, score_threshold: float,
                   output_stride: int = 4) -> dict[str, np.ndarray]:
    """Centres of one frame, best first.

    Args:
        heatmap: (1, 1, H, W) probabilities; offset: (1, 2, H, W) cells (range, angle); doppler: (1, 1, H, W) bins.
        k: most centres kept; score_threshold: least score kept; output_stride: input bins per output cell
            (the manifest's ``detector.output_stride``).

    Returns:
        ``score``, ``range_bin``, ``angle_bin`` (fractional input bins), ``doppler_bin``, each (n,) float32.
    """
    scores = heatmap[0, 0]
    height, width = scores.shape
    windows = sliding_window_view(np.pad(scores, 1, constant_values=-np.inf), (3, 3))  # (H, W, 3, 3)
    peaks = np.where(windows.max(axis=(2, 3)) == scores, scores, 0).reshape(-1)
    best = np.argsort(-peaks, kind="stable")[: min(k, height * width)]
    best = best[peaks[best] >= score_threshold]
    rows, cols = np.divmod(best, width)
    return {
        "score": peaks[best].astype(np.float32),
        "range_bin": ((rows + offset[0, 0].reshape(-1)[best]) * output_stride).astype(np.float32),
        "angle_bin": ((cols + offset[0, 1].reshape(-1)[best]) * output_stride).astype(np.float32),
        "doppler_bin": doppler[0, 0].reshape(-1)[best].astype(np.float32),
    }
