"""The ADC frames a client may send with ``?input=adc``: one frame of the served model's radar, in either of the ADC
chain's layouts (radar.adc: ``"sck"`` (samples, chirps, virtual elements) or ``"ti"`` (chirps, rx, samples)), its
samples complex (complex64/complex128) or 16-bit integers with I and Q on a trailing axis of 2 (``(..., 2)``, as
OpenRadar's frames and TI's tools keep them). ``?layout=`` names the layout; without it the shape says (a shape both
layouts share is read as ``"sck"``). Whatever was sent, the model gets the ``"sck"`` layout; the dtype and shape are
checked from the .npy header, before the array is allocated.

Unsigned 16-bit I/Q is taken too, only to be refused by radar.adc_checks with the decoding it needs: such words are
never decoded samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radar.adc import LAYOUTS, adc_shape, ti_to_sck
from radar.input_kind import COMPLEX_DTYPES
from radar.io.npy import NpyHeader
from radar.profiles import RadarProfile

IQ_DTYPES = (np.int16, np.uint16)  # 16-bit words with I and Q on a trailing axis of 2
AXES = {"sck": "(samples, chirps, virtual elements)", "ti": "(chirps, rx, samples)"}


@dataclass(frozen=True)
class AdcFrameInput:
    """The ADC frames a model takes: its radar ``profile``, in the client's ``layout`` (None: by shape)."""

    profile: RadarProfile
    layout: str | None = None

    def shapes(self) -> dict[str, tuple[int, int, int]]:
        """The frame's shape in each layout the client may send (``"sck"`` first)."""
        return {name: adc_shape(self.profile, name) for name in LAYOUTS if self.layout in (None, name)}

    def layout_of(self, header: NpyHeader) -> str | None:
        """The layout a .npy header's dtype and shape fit, None when they fit none."""
        return self.layout_for(header.dtype, header.shape)

    def layout_for(self, dtype: np.dtype, shape: tuple[int, ...]) -> str | None:
        """The layout a frame of ``dtype`` and ``shape`` fits (complex, or 16-bit I/Q on a trailing axis of 2), None
        when it fits none."""
        dtype = dtype.newbyteorder("=")
        if dtype in [np.dtype(d) for d in COMPLEX_DTYPES]:
            shape = tuple(shape)
        elif dtype in [np.dtype(d) for d in IQ_DTYPES] and tuple(shape[-1:]) == (2,):
            shape = tuple(shape[:-1])
        else:
            return None
        return next((name for name, wanted in self.shapes().items() if wanted == shape), None)

    def describe(self) -> str:
        """``a (128, 128, 8) 'sck' (samples, ...) or (256, 4, 128) 'ti' (chirps, ...) ADC frame: complex64/...``."""
        shapes = " or ".join(f"{shape} {name!r} {AXES[name]}" for name, shape in self.shapes().items())
        return (f"a {shapes} ADC frame: complex64/complex128, or int16 with I and Q on a trailing axis of 2 "
                f"(shape + (2,))")

    def to_sck(self, frame: np.ndarray, layout: str) -> np.ndarray:
        """``frame`` (checked by :meth:`layout_of`) as complex samples in the ``"sck"`` layout: 16-bit I/Q become
        complex64, complex samples keep their dtype."""
        if not np.iscomplexobj(frame):
            frame = (frame[..., 0].astype(np.float32) + 1j * frame[..., 1].astype(np.float32)).astype(np.complex64)
        return ti_to_sck(frame, self.profile) if layout == "ti" else frame
