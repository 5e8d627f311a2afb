"""The RA and RD views of an uploaded cube (``POST /v1/segment?outputs=views``): what a client draws the
predicted masks over, small enough to send with them (uint8 per bin, with the dB range and the physical
value of every bin)."""

from __future__ import annotations

import numpy as np

from radar.profiles import RadarProfile
from service.encoding import encode_array
from service.schemas import InputView, InputViews, MaskEncoding, ViewAxes


def quantize_view(view_db: np.ndarray, encoding: MaskEncoding) -> InputView:
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


def input_views(ra_db: np.ndarray, rd_db: np.ndarray, profile: RadarProfile, encoding: MaskEncoding) -> InputViews:
    """The answer's views from the model's RA view (R, A) and RD view (R, D) of the input in dB
    (``SegmentationResult.views``: computed by the model from the log power it segmented, so raw ADC is processed
    once and the views are part of the request's compute)."""
    return InputViews(ra=quantize_view(ra_db, encoding), rd=quantize_view(rd_db, encoding), axes=view_axes(profile))
