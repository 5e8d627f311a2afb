"""Doppler of detected centres refined from the cube's own Doppler profile.

The learned detector sees the Doppler axis only through the paper's 1x1 compression of D bins to
3 channels, so its Doppler estimate is coarse (mean L1 error about 1.1 bins on fresh ``small``
frames). The cube still holds each object's Doppler profile at the detected cell: this module
replaces the estimate by the power-weighted centroid of the Doppler bins near it.

For a centre at (range ``r``, angle ``a``, Doppler ``d``), the box ``r +- range_bins``,
``a +- angle_bins``, Doppler ``round(d) +- doppler_bins`` (wrapped: the Doppler axis is circular)
is read from the log-power cube; each voxel weighs its dB above ``noise + floor_db`` (0 below) and
the new Doppler is the weighted mean of the box's Doppler bins, wrapped into ``[0, D)``. The window
is kept narrow so that a neighbouring object or the static clutter at zero velocity cannot pull the
estimate; a box with no voxel above the floor keeps the detector's value.

Defaults from a search on 192 frames of freshly simulated ``small`` sequences (seed 777002, shipped
detector; AP@1 / mAP): detector alone 0.195 / 0.552; this centroid (+-4, +-4, +-2, 6 dB) 0.267 /
0.579; the argmax of the box's Doppler profile 0.13-0.15 / 0.51 (it lands on one scatterer, while the
labelled Doppler is the mean over the object's voxels); voxel counts instead of dB weights 0.25 /
0.575; iterating the centroid did not help; with the true Doppler in place of any estimate 0.361 / 0.622.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar.centres import Centres
from radar.region_growing import noise_level_db


@dataclass(frozen=True)
class DopplerRefinement:
    """Half-widths of the box read around each centre (bins) and the weights' floor (dB above noise)."""

    range_bins: int = 4
    angle_bins: int = 4
    doppler_bins: int = 2  # window around the detector's estimate: the estimate is within ~1 bin
    floor_db: float = 6.0  # simulated labels start at noise + 6 dB

    def __post_init__(self) -> None:
        for name in ("range_bins", "angle_bins", "doppler_bins"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 0:
                raise ValueError(f"DopplerRefinement.{name} must be an int >= 0, got {value!r}")
        if not np.isfinite(self.floor_db):
            raise ValueError(f"DopplerRefinement.floor_db must be finite, got {self.floor_db}")


def refine_doppler(log_power: np.ndarray, centres: Centres, config: DopplerRefinement | None = None, *,
                   noise_db: float | None = None) -> Centres:
    """``centres`` with each Doppler bin replaced by the centroid of the cube's Doppler profile near it.

    Args:
        log_power: (R, A, D) log power in dB.
        centres: detected centres (fractional bins); score, range and angle are kept.
        config: box half-widths and floor (default :class:`DopplerRefinement`).
        noise_db: the frame's noise level in dB (default :func:`radar.region_growing.noise_level_db`).

    Returns:
        New :class:`Centres` (same order) with Doppler bins in ``[0, D)``.
    """
    config = config or DopplerRefinement()
    if log_power.ndim != 3:
        raise ValueError(f"log_power must be (R, A, D), got shape {log_power.shape}")
    if len(centres) == 0:
        return centres
    if not np.isfinite(centres.bins).all():
        raise ValueError("centres must have finite (range, angle, Doppler) bins")
    n_range, n_angle, n_doppler = log_power.shape
    if noise_db is None:
        noise_db = noise_level_db(log_power)
    offsets = np.arange(-config.doppler_bins, config.doppler_bins + 1)
    doppler = np.asarray(centres.doppler_bin, np.float64).copy()
    for i, (range_bin, angle_bin, doppler_bin) in enumerate(centres.bins):
        r0 = int(np.clip(np.rint(range_bin), 0, n_range - 1))
        a0 = int(np.clip(np.rint(angle_bin), 0, n_angle - 1))
        window = int(np.rint(doppler_bin)) + offsets  # (W,) unwrapped Doppler bins
        box = log_power[max(r0 - config.range_bins, 0):r0 + config.range_bins + 1,
                        max(a0 - config.angle_bins, 0):a0 + config.angle_bins + 1][:, :, window % n_doppler]
        weight = np.clip(box - (noise_db + config.floor_db), 0.0, None).sum(axis=(0, 1))  # (W,) dB above floor
        if weight.sum() > 0:
            doppler[i] = float((weight * window).sum() / weight.sum())
    return Centres(centres.score, centres.range_bin, centres.angle_bin, np.mod(doppler, n_doppler))


DOPPLER_REFINEMENT = DopplerRefinement()  # the default applied by models.erasenet.model.EraseNet and the AP scorers
