"""A DCA1000 capture (``adc_data.bin``) as the body of ``POST /v1/segment?input=adc&format=dca1000``: the frames'
16-bit words back to back, read with the served model's radar profile (frame size, LVDS lanes, I/Q order, offset
binary: its ``[capture]`` table, radar/ti/capture.py). One frame (``?frame=K``, the first by default) is decoded and
handed on in the ADC chain's ``"sck"`` layout; the others are never decoded.

The body is bounded by ``max_body_bytes`` (a chunked body is charged to its upload ticket as it arrives); a body
that is not whole frames of the radar is refused with the capture reader's one line (the bytes, the bytes a frame
takes, the likely cause), and so is a frame index past the capture's last frame.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from dataclasses import dataclass

import numpy as np
from starlette.requests import ClientDisconnect, Request

from radar.adc import ti_to_sck
from radar.errors import DataError
from radar.profiles import RadarProfile
from radar.ti.capture import frames_from_bytes
from radar.ti.dca1000 import CaptureFormat, FrameGeometry
from service.http.errors import ApiError
from service.inputs.upload import ExpectedCube, UploadGate, UploadTicket, check_values, paced
from service.settings import Settings

SOURCE = "capture"  # how the reader's lines name the body


@dataclass(frozen=True)
class CaptureFrame:
    """The chosen frame of an uploaded capture (``"sck"`` layout, complex64) and the capture's whole frames."""

    adc: np.ndarray
    index: int
    frames: int


def _refusal(exc: DataError) -> ApiError:
    return ApiError(422, str(exc), error="invalid_capture")


async def read_capture(chunks: AsyncIterator[bytes], profile: RadarProfile, *, frame: int, limit: int,
                       content_length: int | None, ticket: UploadTicket | None = None) -> CaptureFrame:
    """Frame ``frame`` of the DCA1000 capture in ``chunks``, for ``profile``.

    Raises ApiError 413 (more than ``limit`` bytes), 422 ``invalid_capture`` (a format the radar cannot have, a body
    that is not whole frames, a frame index past the last frame) or 400 (an empty body)."""
    fmt = CaptureFormat.of_profile(profile)
    geometry = FrameGeometry.of_profile(profile, fmt)
    if problem := geometry.layout_problem(fmt):  # refused before the body is read
        raise ApiError(422, f"{SOURCE}: {fmt.describe()}: {problem}", error="invalid_capture")
    data = bytearray()
    async for chunk in chunks:
        if len(data) + len(chunk) > limit:
            raise ApiError(413, f"capture of more than {limit} bytes: the service takes at most {limit} bytes a "
                                f"request (whole frames of {geometry.bytes} bytes: at most {limit // geometry.bytes})",
                           headers={"Connection": "close"})
        data += chunk
        if ticket is not None and content_length is None:
            ticket.charge(len(data))
    if not data:
        raise ApiError(400, "body is empty: send the capture's bytes (adc_data.bin)", error="invalid_capture")
    size, frame_bytes = len(data), geometry.bytes
    try:
        if size < frame_bytes or size % frame_bytes:
            frames_from_bytes(data, profile, fmt, source=SOURCE)  # the reader's one line on what does not fit
        frames = size // frame_bytes
        if frame >= frames:
            raise DataError(SOURCE, f"frame {frame} out of range: the capture holds {frames} whole frame"
                                    f"{'s' if frames > 1 else ''} of {frame_bytes} bytes (frames 0 to {frames - 1})")
        view = memoryview(data)[frame * frame_bytes:(frame + 1) * frame_bytes]
        decoded = frames_from_bytes(view, profile, fmt, source=SOURCE)[0]  # (chirps, rx, samples) complex64
    except DataError as exc:
        raise _refusal(exc) from None
    return CaptureFrame(ti_to_sck(decoded, profile), frame, frames)


async def read_capture_body(request: Request, uploads: UploadGate, settings: Settings, tenant: str,
                            expected: ExpectedCube, content_length: int | None, frame: int
                            ) -> tuple[CaptureFrame, float]:
    """The chosen frame of the capture in the request's body, checked as any ADC frame (undecoded words refused:
    radar.adc_checks), and the seconds spent receiving and decoding it; the body held in ``uploads`` meanwhile."""
    assert expected.adc is not None, "a capture is read for ?input=adc"
    start = time.perf_counter()
    with uploads.admit(tenant, content_length) as ticket:
        try:
            capture = await read_capture(paced(request.stream(), settings), expected.adc.profile, frame=frame,
                                         limit=settings.max_body_bytes, content_length=content_length, ticket=ticket)
        except ClientDisconnect:
            raise ApiError(400, "client disconnected before sending the whole body") from None
    check_values(capture.adc, expected)
    return capture, time.perf_counter() - start
