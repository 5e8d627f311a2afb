"""CA/OS-CFAR centre detection: the non-learned baseline of stage 1 (docs/design.md section 5).

CFAR runs on the RD view (power averaged over the array), where the array gain lifts objects out of
the noise; 3-D CFAR on the RAD cube drowns in angle sidelobes. Each RD detection then takes the
angle of its strongest bin, detections of one object are merged, and the result has the detector's
output type (:class:`radar.centres.Centres`, score = SNR in dB over the CFAR noise estimate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from radar.centres import Centres
from radar.profiles import RadarProfile


@dataclass(frozen=True)
class CfarConfig:
    method: str = "ca"  # "ca": cell averaging; "os": ordered statistic
    guard: tuple[int, int] = (2, 2)  # guard half-widths (range, Doppler bins)
    train: tuple[int, int] = (8, 4)  # training half-widths beyond the guard cells
    threshold_db: float = 13.0  # detection threshold over the noise estimate
    os_quantile: float = 0.75  # OS-CFAR: the noise estimate is this quantile of the training cells
    static_notch_bins: int = 1  # drop detections within this many bins of zero Doppler (clutter); -1 keeps all
    merge_m: float = 2.5  # detections closer than this (x-y metres) ...
    merge_doppler_bins: float = 4.0  # ... and this in Doppler belong to one object
    max_detections: int = 64

    def __post_init__(self) -> None:
        if self.method not in ("ca", "os"):
            raise ValueError(f"CFAR method must be 'ca' or 'os', got {self.method!r}")
        if min(self.guard) < 0 or min(self.train) < 1:
            raise ValueError(f"guard must be >= 0 and train >= 1 cells, got {self.guard} and {self.train}")


def _training_footprint(config: CfarConfig) -> np.ndarray:
    (gr, gd), (tr, td) = config.guard, config.train
    footprint = np.ones((2 * (gr + tr) + 1, 2 * (gd + td) + 1), bool)
    footprint[tr:tr + 2 * gr + 1, td:td + 2 * gd + 1] = False
    return footprint


def cfar_noise(rd_power: np.ndarray, config: CfarConfig) -> np.ndarray:
    """Noise power estimate (R, D) of every RD cell from its training cells (Doppler wraps)."""
    footprint = _training_footprint(config)
    modes = ("nearest", "wrap")
    if config.method == "os":  # rank filters take one mode: pad by hand (edge in range, wrap in Doppler)
        pr, pd = footprint.shape[0] // 2, footprint.shape[1] // 2
        padded = np.pad(np.pad(rd_power, ((pr, pr), (0, 0)), mode="edge"), ((0, 0), (pd, pd)), mode="wrap")
        filtered = ndimage.percentile_filter(padded, 100 * config.os_quantile, footprint=footprint)
        return filtered[pr:-pr, pd:-pd]
    outer = ndimage.uniform_filter(rd_power, size=footprint.shape, mode=modes) * footprint.size
    (gr, gd) = config.guard
    inner = ndimage.uniform_filter(rd_power, size=(2 * gr + 1, 2 * gd + 1), mode=modes) * (2 * gr + 1) * (2 * gd + 1)
    return (outer - inner) / footprint.sum()


def cfar_centres(log_power: np.ndarray, profile: RadarProfile, config: CfarConfig | None = None) -> Centres:
    """Object centres of a log-power cube (R, A, D) by CFAR on its RD view, then the angle peak."""
    config = config or CfarConfig()
    if log_power.shape != profile.shape:
        raise ValueError(f"log-power cube must have shape {profile.shape}, got {log_power.shape}")
    power = np.power(np.float32(10.0), log_power / np.float32(10.0)) - 1.0  # |I|^2
    rd_power = power.mean(axis=1)  # (R, D)
    noise = np.maximum(cfar_noise(rd_power, config), 1e-12)
    snr_db = 10 * np.log10(np.maximum(rd_power, 1e-12) / noise)
    peaks = (snr_db >= config.threshold_db) & (rd_power == ndimage.maximum_filter(rd_power, size=3, mode="nearest"))
    if config.static_notch_bins >= 0:
        zero = profile.n_doppler // 2
        peaks[:, zero - config.static_notch_bins:zero + config.static_notch_bins + 1] = False
    r, d = np.nonzero(peaks)
    order = np.argsort(-snr_db[r, d])
    r, d = r[order], d[order]
    a = np.argmax(log_power[r, :, d], axis=1)
    x, y = profile.xy(r, a)
    keep: list[int] = []
    for i in range(len(r)):  # greedy merge by descending SNR: loops over detections, not voxels
        if len(keep) >= config.max_detections:
            break
        close = [(x[i] - x[j]) ** 2 + (y[i] - y[j]) ** 2 <= config.merge_m**2
                 and abs(d[i] - d[j]) <= config.merge_doppler_bins for j in keep]
        if not any(close):
            keep.append(i)
    k = np.array(keep, dtype=np.int64)
    return Centres(snr_db[r[k], d[k]].astype(np.float64), r[k].astype(np.float64), a[k].astype(np.float64),
                   d[k].astype(np.float64))
