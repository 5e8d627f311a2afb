"""Log power, the 2-D views of a RAD cube, and projections of RAD labels to RA and RD masks."""

from __future__ import annotations

import numpy as np


def power(cube: np.ndarray) -> np.ndarray:
    """|I|^2 as float32; a real cube is taken as a magnitude."""
    if np.iscomplexobj(cube):
        return (cube.real.astype(np.float32) ** 2 + cube.imag.astype(np.float32) ** 2)
    return np.square(cube, dtype=np.float32)


def log_power(cube: np.ndarray) -> np.ndarray:
    """The model input ``10*log10(|I|^2 + 1)`` in dB, float32, same shape (R, A, D)."""
    return 10.0 * np.log10(power(cube) + 1.0)


def ra_view(cube: np.ndarray, *, is_log_power: bool = False) -> np.ndarray:
    """RA view (R, A): max of log power over Doppler (dB)."""
    lp = cube if is_log_power else log_power(cube)
    return lp.max(axis=2)


def rd_view(cube: np.ndarray, *, is_log_power: bool = False) -> np.ndarray:
    """RD view (R, D): log of the power summed over the virtual array, in dB.

    Summing ``|I|^2`` over the ``A`` zero-padded angle bins gives ``A`` times the power summed over
    the array elements (Parseval); dividing by ``A`` makes this CARRADA's RD convention (they undo
    the angle FFT and sum over antennas), so the dB scale is comparable.
    """
    p = np.power(10.0, cube / 10.0, dtype=np.float32) - 1.0 if is_log_power else power(cube)
    return 10.0 * np.log10(p.sum(axis=1) / cube.shape[1] + 1.0)


def ad_view(cube: np.ndarray, *, is_log_power: bool = False) -> np.ndarray:
    """AD view (A, D): max of log power over range (dB)."""
    lp = cube if is_log_power else log_power(cube)
    return lp.max(axis=0)


def _project(labels: np.ndarray, axis: int, num_classes: int) -> np.ndarray:
    """Majority foreground class along ``axis``; background where no foreground voxel lies."""
    counts = np.stack([(labels == c).sum(axis=axis) for c in range(1, num_classes)], axis=0)
    best = counts.argmax(axis=0) + 1
    return np.where(counts.max(axis=0) > 0, best, 0).astype(np.uint8)


def project_ra(labels: np.ndarray, num_classes: int) -> np.ndarray:
    """RA mask (R, A) uint8 of a RAD class cube: per cell the object class with the most voxels along
    Doppler, background if none (SPEC section 8). Ties go to the lower class id."""
    return _project(labels, axis=2, num_classes=num_classes)


def project_rd(labels: np.ndarray, num_classes: int) -> np.ndarray:
    """RD mask (R, D) uint8: the same rule along angle."""
    return _project(labels, axis=1, num_classes=num_classes)
