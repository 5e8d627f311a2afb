"""The RA and RD views of an uploaded cube (``POST /v1/segment?outputs=views``): what a client draws the
predicted masks over, small enough to send with them (uint8 per bin, with the dB range and the physical
value of every bin)."""

from __future__ import annotations

import numpy as np

from radar import transforms
from radar.adc import process_adc
from radar.profiles import RadarProfile
from service.encoding import encode_array
from service.schemas import InputKind, InputView, InputViews, MaskEncoding, ViewAxes


def quantise_view(view_db: np.ndarray, encoding: MaskEncoding) -> InputView:
    """A view in dB as uint8 over its own [min, max]; ``dB = low_db + value * (high_db - low_db) / 255``."""
    low, high = float(view_db.min()), float(view_db.max())
    span = high - low if high > low else 1.0
    levels = np.rint((view_db - low) * (255.0 / span)).astype(np.uint8)
    return InputView(low_db=round(low, 3), high_db=round(low + span, 3), array=encode_array(levels, encoding))


def view_axes(profile: RadarProfile) -> ViewAxes:
    """Bin centres: range (m) per range bin, azimuth (deg) per angle bin, radial velocity (m/s) per Doppler bin."""
    n_range, n_angle, n_doppler = profile.shape

    def values(array: np.ndarray) -> list[float]:
        return [round(float(v), 4) for v in array]

    return ViewAxes(range_m=values(profile.range_m(np.arange(n_range))),
                    angle_deg=values(profile.angle_deg(np.arange(n_angle))),
                    velocity_mps=values(profile.velocity_mps(np.arange(n_doppler))))


def input_views(cube: np.ndarray, profile: RadarProfile, input_kind: InputKind, encoding: MaskEncoding, *,
                tdm_compensation: bool = True) -> InputViews:
    """RA view (R, A) and RD view (R, D) of a validated upload: a complex RAD cube, its log power in dB, or raw
    ADC samples (processed again here, as the model did)."""
    if input_kind is InputKind.adc:
        cube = process_adc(cube, profile, tdm_compensation=tdm_compensation)
    log_power = cube.astype(np.float32, copy=False) if input_kind is InputKind.log_power else transforms.log_power(cube)
    return InputViews(ra=quantise_view(transforms.ra_view(log_power, is_log_power=True), encoding),
                      rd=quantise_view(transforms.rd_view(log_power, is_log_power=True), encoding),
                      axes=view_axes(profile))
