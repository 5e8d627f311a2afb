"""Exact labels from each object's own noiseless response (docs/design.md section 3.1).

A voxel belongs to object ``o`` when ``o``'s response there is the largest of all objects', is at
least ``snr_db`` above the mean noise power per voxel, and is within ``peak_db`` of ``o``'s own peak.
Static clutter is not an object: it never takes a voxel from one (it is background by definition).

Each object's response is evaluated only in a window around its scatterers: ``margin_cells``
resolution cells beyond the outermost scatterer on each axis (4 cells keeps the Hann main lobe and
its first two sidelobes; what is cut is below about -45 dB of the scatterer's peak). Windows wrap
around every axis, as the FFTs do.
"""

from __future__ import annotations

import numpy as np

from radar.profiles import RadarProfile
from radar.simulate.fmcw import Scatterers, axis_kernels


def _axis_window(centres: np.ndarray, margin: int, size: int) -> np.ndarray:
    lo = int(np.floor(centres.min())) - margin
    hi = int(np.ceil(centres.max())) + margin
    if hi - lo + 1 >= size:
        return np.arange(size)
    return np.arange(lo, hi + 1) % size


def object_response_window(profile: RadarProfile, scat: Scatterers, *, tdm_coupling: bool = False,
                           margin_cells: int = 4, channel_gains: np.ndarray | None = None,
                           ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], np.ndarray]:
    """Noiseless power |response|^2 of one object's scatterers inside its window.

    Returns ``((range_idx, angle_idx, doppler_idx), power)`` with ``power`` of shape
    (len(range_idx), len(angle_idx), len(doppler_idx)) float32.
    """
    kr, ka, kd = axis_kernels(profile, scat, tdm_coupling=tdm_coupling, channel_gains=channel_gains)
    range_bins = scat.range_m / profile.range_res
    angle_bins = profile.angle_bin_from_sin(scat.sin_theta)
    doppler_bins = profile.doppler_bin(scat.radial_velocity)
    wr = _axis_window(range_bins, margin_cells * profile.range_pad, profile.n_range)
    wa = _axis_window(angle_bins, int(np.ceil(margin_cells * profile.n_angle / profile.n_virtual)), profile.n_angle)
    wd = _axis_window(doppler_bins, margin_cells * profile.doppler_pad, profile.n_doppler)
    n = len(scat)
    left = (kr[:, wr] * scat.amplitude[:, None]).T.astype(np.complex64)  # (Wr, P)
    right = (ka[:, wa][:, :, None] * kd[:, wd][:, None, :]).reshape(n, -1).astype(np.complex64)  # (P, Wa*Wd)
    resp = (left @ right).reshape(len(wr), len(wa), len(wd))
    power = resp.real**2 + resp.imag**2
    return (wr, wa, wd), power


def exact_labels(profile: RadarProfile, objects: list[Scatterers], class_ids: list[int], *,
                 snr_db: float = 6.0, peak_db: float = 20.0, tdm_coupling: bool = False,
                 margin_cells: int = 4, channel_gains: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Class cube and instance cube, both (R, A, D) uint8; object ``i`` gets instance id ``i + 1``. Each object's
    response is the one the frame was synthesised with: its TDM coupling and channel errors (``channel_gains``)."""
    if len(objects) != len(class_ids):
        raise ValueError(f"{len(objects)} objects but {len(class_ids)} class ids")
    if len(objects) > 255:
        raise ValueError(f"at most 255 objects per frame fit the uint8 instance cube, got {len(objects)}")
    floor = 10 ** ((profile.noise_floor_db + snr_db) / 10)
    best_power = np.zeros(profile.shape, np.float32)
    best_id = np.zeros(profile.shape, np.uint8)
    passes = np.zeros(profile.shape, bool)
    for i, scat in enumerate(objects):
        if len(scat) == 0:
            continue
        (wr, wa, wd), power = object_response_window(profile, scat, tdm_coupling=tdm_coupling,
                                                     margin_cells=margin_cells, channel_gains=channel_gains)
        ok = (power >= floor) & (power >= power.max() * 10 ** (-peak_db / 10))
        idx = np.ix_(wr, wa, wd)
        larger = power > best_power[idx]
        best_power[idx] = np.where(larger, power, best_power[idx])
        best_id[idx] = np.where(larger, np.uint8(i + 1), best_id[idx])
        passes[idx] = np.where(larger, ok, passes[idx])
    instances = np.where(passes, best_id, np.uint8(0))
    lut = np.zeros(256, np.uint8)
    lut[1:len(class_ids) + 1] = class_ids
    return lut[instances], instances
