"""Per-instance statistics of a labelled RAD cube: voxel counts, centres and mean Doppler.

The centre of an object is the mean Cartesian position of its labelled voxels, mapped back to
fractional (range, angle) bins; its Doppler is the circular mean of its voxels' Doppler bins (the
Doppler axis wraps). These are the detector's targets (docs/design.md section 5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar.profiles import RadarProfile


@dataclass(frozen=True)
class InstanceStats:
    """Arrays indexed by instance id (index 0 = background, unused). NaN where an id has no voxel."""

    n_voxels: np.ndarray  # (N+1,) int64
    x: np.ndarray  # mean lateral position (m)
    y: np.ndarray  # mean forward position (m)
    range_bin: np.ndarray  # fractional range bin of (x, y)
    angle_bin: np.ndarray  # fractional angle bin of (x, y)
    doppler_bin: np.ndarray  # circular mean Doppler bin in [0, D)


def instance_stats(instances: np.ndarray, profile: RadarProfile, n_instances: int | None = None) -> InstanceStats:
    """Statistics of every instance id in an (R, A, D) instance cube (0 = background)."""
    if instances.shape != profile.shape:
        raise ValueError(f"instance cube must have shape {profile.shape}, got {instances.shape}")
    r, a, d = np.nonzero(instances)
    ids = instances[r, a, d].astype(np.int64)
    size = (int(ids.max()) if len(ids) else 0) + 1
    if n_instances is not None:
        size = max(size, n_instances + 1)
    cart_x, cart_y = profile.ra_cartesian
    count = np.bincount(ids, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        x = np.bincount(ids, weights=cart_x[r, a], minlength=size) / count
        y = np.bincount(ids, weights=cart_y[r, a], minlength=size) / count
        phase = 2 * np.pi * d / profile.n_doppler
        c = np.bincount(ids, weights=np.cos(phase), minlength=size)
        s = np.bincount(ids, weights=np.sin(phase), minlength=size)
    doppler = np.mod(np.arctan2(s, c) / (2 * np.pi) * profile.n_doppler, profile.n_doppler)
    doppler[count == 0] = np.nan
    range_bin, angle_bin = profile.bins_from_xy(x, y)
    return InstanceStats(count, x, y, range_bin, angle_bin, doppler)
