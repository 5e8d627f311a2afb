"""From ROI voxels to the points the sparse segmenter labels (docs/design.md section 7).

Every ROI voxel becomes a point with four features, each scaled to about [-1, 1]:
``x / max_range``, ``y / max_range`` (Cartesian metres of its RA cell), ``v / max_velocity`` (radial
velocity of its Doppler bin) and the normalised log power ``(lp - mean) / std``.

Coordinates are the voxel's own (range, angle, Doppler) bins by default: no two voxels collide and
neighbours in the cube are neighbours in the sparse tensor. ``voxel_size_m`` switches to Cartesian
voxels of that size in x and y (Doppler bin kept as the third axis); voxels that fall into the same
Cartesian cell are merged (features averaged) and ``inverse`` maps each ROI voxel to its point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar.profiles import RadarProfile

N_FEATURES = 4


@dataclass(frozen=True)
class RoiPoints:
    """Points of one frame: ``coords`` (P, 3) int64, ``features`` (P, 4) float32, ``inverse`` (N,)
    int64 row of ``coords`` for each of the N ROI voxels (identity with bin coordinates)."""

    coords: np.ndarray
    features: np.ndarray
    inverse: np.ndarray

    def __len__(self) -> int:
        return len(self.coords)


def voxel_features(voxels: np.ndarray, log_power: np.ndarray, profile: RadarProfile, *,
                   mean_db: float = 0.0, std_db: float = 1.0) -> np.ndarray:
    """(N, 4) float32 features of ROI voxels (N, 3) (range, angle, Doppler bins)."""
    r, a, d = voxels.T
    cart_x, cart_y = profile.ra_cartesian
    return np.stack([
        cart_x[r, a] / profile.max_range,
        cart_y[r, a] / profile.max_range,
        profile.velocity_mps(d) / profile.max_velocity,
        (log_power[r, a, d] - mean_db) / std_db,
    ], axis=1).astype(np.float32)


def roi_points(voxels: np.ndarray, log_power: np.ndarray, profile: RadarProfile, *, mean_db: float = 0.0,
               std_db: float = 1.0, voxel_size_m: float | None = None) -> RoiPoints:
    """Points of the ROI voxels (N, 3); see the module docstring for coordinates and features."""
    voxels = np.asarray(voxels, dtype=np.int64).reshape(-1, 3)
    features = voxel_features(voxels, log_power, profile, mean_db=mean_db, std_db=std_db)
    if voxel_size_m is None:
        return RoiPoints(voxels, features, np.arange(len(voxels), dtype=np.int64))
    if voxel_size_m <= 0:
        raise ValueError(f"voxel_size_m must be > 0, got {voxel_size_m}")
    cart_x, cart_y = profile.ra_cartesian
    r, a, d = voxels.T
    cells = np.stack([np.floor(cart_x[r, a] / voxel_size_m), np.floor(cart_y[r, a] / voxel_size_m), d], axis=1)
    coords, inverse = np.unique(cells.astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    counts = np.bincount(inverse, minlength=len(coords)).astype(np.float32)
    merged = np.zeros((len(coords), N_FEATURES), np.float32)
    np.add.at(merged, inverse, features)
    return RoiPoints(coords, merged / counts[:, None], inverse)
