"""Log power, the 2-D views of a RAD cube, and projections of RAD labels to RA and RD masks."""

from __future__ import annotations

import numpy as np

from radar.input_kind import InputKind


def power(cube: np.ndarray) -> np.ndarray:
    """|I|^2 as float32; a real cube is taken as a magnitude."""
    if np.iscomplexobj(cube):
        return (cube.real.astype(np.float32) ** 2 + cube.imag.astype(np.float32) ** 2)
    return np.square(cube, dtype=np.float32)


def log_power(cube: np.ndarray) -> np.ndarray:
    """The model input ``10*log10(|I|^2 + 1)`` in dB, float32, same shape (R, A, D).

    One new array, every later step in place (abs, square, +1, log2, scale): about half the time of
    the expression form, which allocates a temporary per operation.
    """
    if np.iscomplexobj(cube) and cube.dtype == np.complex64:
        out = np.abs(cube)  # float32
        np.square(out, out=out)
    else:
        out = power(cube)
    out += 1.0
    np.log2(out, out=out)
    out *= np.float32(10.0 * np.log10(2.0))
    return out


def to_log_power(cube: np.ndarray, kind: InputKind = InputKind.complex) -> np.ndarray:
    """The model input (float32 log power in dB) of a RAD cube that holds ``kind``: log power is taken as it is
    (no copy when already float32), a complex or magnitude cube goes through :func:`log_power`. ADC samples are
    not a RAD cube: :mod:`radar.adc` makes one first."""
    if kind is InputKind.log_power:
        return cube.astype(np.float32, copy=False)
    if kind is InputKind.adc:
        raise ValueError("ADC samples are not a RAD cube: process them with radar.adc first")
    return log_power(cube)


def ra_view(cube: np.ndarray, *, kind: InputKind = InputKind.complex) -> np.ndarray:
    """RA view (R, A): max of log power over Doppler (dB)."""
    return to_log_power(cube, kind).max(axis=2)


def rd_view(cube: np.ndarray, *, kind: InputKind = InputKind.complex) -> np.ndarray:
    """RD view (R, D): log of the power summed over the virtual array, in dB.

    Summing ``|I|^2`` over the ``A`` zero-padded angle bins gives ``A`` times the power summed over
    the array elements (Parseval); dividing by ``A`` makes this CARRADA's RD convention (they undo
    the angle FFT and sum over antennas), so the dB scale is comparable.
    """
    if kind is InputKind.log_power:
        p = np.power(10.0, cube / 10.0, dtype=np.float32) - 1.0
    elif kind is InputKind.adc:
        raise ValueError("ADC samples are not a RAD cube: process them with radar.adc first")
    else:
        p = power(cube)
    return 10.0 * np.log10(p.sum(axis=1) / cube.shape[1] + 1.0)


def ad_view(cube: np.ndarray, *, kind: InputKind = InputKind.complex) -> np.ndarray:
    """AD view (A, D): max of log power over range (dB)."""
    return to_log_power(cube, kind).max(axis=0)


def _project(labels: np.ndarray, axis: int, num_classes: int) -> np.ndarray:
    """Majority foreground class along ``axis``; background where no foreground voxel lies."""
    counts = np.stack([(labels == c).sum(axis=axis) for c in range(1, num_classes)], axis=0)
    best = counts.argmax(axis=0) + 1
    return np.where(counts.max(axis=0) > 0, best, 0).astype(np.uint8)


def project_voxels(voxels: np.ndarray, classes: np.ndarray, shape: tuple[int, int, int], axis: int,
                   num_classes: int) -> np.ndarray:
    """``_project`` of a cube that is background except at ``voxels``, reading only those voxels.

    Args:
        voxels: (N, 3) int (range, angle, Doppler) bins, unique.
        classes: (N,) class of each voxel (0 = background).
        shape: the cube's (R, A, D).
        axis: the axis projected away (2: RA mask, 1: RD mask).
        num_classes: classes, background included.

    Returns:
        The 2-D mask (uint8), equal to ``_project`` of the dense cube (ties to the lower class id).
    """
    kept = [a for a in range(3) if a != axis]
    plane = (shape[kept[0]], shape[kept[1]])
    foreground = classes > 0
    cells = voxels[foreground][:, kept[0]] * plane[1] + voxels[foreground][:, kept[1]]
    counts = np.bincount(cells * num_classes + classes[foreground].astype(np.int64),
                         minlength=plane[0] * plane[1] * num_classes).reshape(plane[0] * plane[1], num_classes)
    best = counts[:, 1:].argmax(axis=1) + 1  # argmax keeps the first maximum: the lower class id
    mask = np.where(counts[:, 1:].max(axis=1) > 0, best, 0).astype(np.uint8)
    return mask.reshape(plane)


def project_ra(labels: np.ndarray, num_classes: int) -> np.ndarray:
    """RA mask (R, A) uint8 of a RAD class cube: per cell the object class with the most voxels along
    Doppler, background if none (docs/design.md section 8). Ties go to the lower class id."""
    return _project(labels, axis=2, num_classes=num_classes)


def project_rd(labels: np.ndarray, num_classes: int) -> np.ndarray:
    """RD mask (R, D) uint8: the same rule along angle."""
    return _project(labels, axis=1, num_classes=num_classes)
