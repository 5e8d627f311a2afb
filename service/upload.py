"""Reading an uploaded ``.npy`` cube from a request body stream.

The header is parsed and checked (dtype kind, shape, byte count against ``Content-Length``) as soon
as its bytes have arrived, before the array is allocated; the array is then filled chunk by chunk
(no second copy of a 32 MiB body). Pickled/object arrays are refused by the header parser.

Uploads are bounded before any model is involved: :class:`UploadGate` admits at most ``max_uploads``
bodies, announcing at most ``max_upload_bytes`` together, at once (503 + Retry-After beyond), and
:func:`paced` cuts off a body that falls behind ``body_min_rate`` bytes/s after ``body_grace_s`` seconds,
or is not complete within ``body_timeout_s`` (408, connection closed).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from radar.input_kind import ACCEPTED_DTYPES, InputKindError, resolve_kind
from radar.io.errors import DataError
from radar.io.npy import MAGIC, MAX_HEADER_LEN, NpyHeader, parse_npy_header
from service.errors import ApiError
from service.schemas import InputKind
from service.settings import Settings


@dataclass(frozen=True)
class ExpectedCube:
    """What a model accepts: its cube shape and the input kind the client announced."""

    model: str
    shape: tuple[int, int, int]
    kind: InputKind

    def describe(self) -> str:
        names = "/".join(np.dtype(d).name for d in ACCEPTED_DTYPES[self.kind])
        return f"a {self.shape} {names} .npy cube"


class UploadGate:
    """Bounds the request bodies being received at once: their number and the bytes they announce (what
    the cubes will occupy once allocated; a chunked body counts as ``max_body_bytes``)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.uploads = 0
        self.bytes = 0

    @contextmanager
    def admit(self, content_length: int | None) -> Iterator[None]:
        """Hold a place for one body while it is read; ApiError 503 when the bound is reached."""
        s = self.settings
        size = content_length if content_length is not None else s.max_body_bytes
        if self.uploads >= s.max_uploads or self.bytes + size > s.max_upload_bytes:
            raise ApiError(503, f"{self.uploads} uploads of {self.bytes} bytes in progress (limits: {s.max_uploads} "
                                f"uploads, {s.max_upload_bytes} bytes); try again later", error="uploads_saturated",
                           headers={"Retry-After": str(s.retry_after_s)})
        self.uploads += 1
        self.bytes += size
        try:
            yield
        finally:
            self.uploads -= 1
            self.bytes -= size


async def paced(chunks: AsyncIterator[bytes], settings: Settings) -> AsyncIterator[bytes]:
    """``chunks`` as they arrive, or ApiError 408 when the body falls behind ``body_min_rate`` after
    ``body_grace_s`` (the next bytes are due by ``start + grace + received / rate``) or is not complete
    within ``body_timeout_s``."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    deadline = start + settings.body_timeout_s
    received = 0
    iterator = aiter(chunks)
    while True:
        due = min(deadline, start + settings.body_grace_s + received / settings.body_min_rate)
        try:
            async with asyncio.timeout_at(due):
                chunk = await anext(iterator)
        except StopAsyncIteration:
            return
        except TimeoutError:
            elapsed = loop.time() - start
            why = (f"not complete within {settings.body_timeout_s:g} s" if due >= deadline else
                   f"below the minimum rate of {settings.body_min_rate} bytes/s after {settings.body_grace_s:g} s")
            raise ApiError(408, f"request body {why}: {received} bytes in {elapsed:.1f} s", error="body_timeout",
                           headers={"Connection": "close"}) from None
        received += len(chunk)
        yield chunk


def _header_length(head: bytes | bytearray) -> int | None:
    """Bytes needed for the whole header, or None until the length field has arrived."""
    if not MAGIC.startswith(bytes(head[:len(MAGIC)])):  # also a body shorter than the magic string ("hello")
        raise ApiError(400, "body is not a .npy file (missing the \\x93NUMPY magic string)", error="malformed_npy")
    if len(head) < 12:
        return None
    major = head[6]
    if major == 1:
        start, length = 10, int.from_bytes(head[8:10], "little")
    elif major in (2, 3):
        start, length = 12, int.from_bytes(head[8:12], "little")
    else:
        raise ApiError(400, f"unsupported .npy format version {major}", error="malformed_npy")
    if length > MAX_HEADER_LEN:  # refused before waiting for (and buffering) its bytes
        raise ApiError(400, f"oversized .npy header: {length} bytes, at most {MAX_HEADER_LEN} accepted",
                       error="malformed_npy")
    return start + length


def check_header(header: NpyHeader, expected: ExpectedCube, content_length: int | None) -> None:
    """Refuse a header whose dtype, shape or byte count is not what the model takes (before allocation)."""
    if header.dtype.newbyteorder("=") not in [np.dtype(d) for d in ACCEPTED_DTYPES[expected.kind]]:
        try:  # radar.input_kind's rule: a real-valued cube says what it holds
            resolve_kind(header.dtype, expected.kind, flag="?input={}")
            hint = ""
        except InputKindError as exc:
            hint = f" ({exc})"
        raise ApiError(422, f"cube has dtype {header.dtype.name}, model {expected.model!r} expects "
                            f"{expected.describe()}{hint}", error="invalid_cube")
    if header.shape != expected.shape:
        axes = "(samples, chirps, virtual elements)" if expected.kind is InputKind.adc else "(range, angle, Doppler)"
        raise ApiError(422, f"cube has shape {header.shape}, model {expected.model!r} expects {expected.shape} "
                            f"{axes}", error="invalid_cube")
    total = header.data_offset + header.nbytes
    if content_length is not None and content_length != total:
        raise ApiError(400, f"body is {content_length} bytes but its .npy header ({header.shape} "
                            f"{header.dtype.name}) needs {total}", error="malformed_npy")


def _all_finite(cube: np.ndarray) -> bool:
    """NaN/Inf check in one pass without a boolean temporary: a float64 sum of finite float16/32 values cannot
    overflow, and NaN or Inf propagate into it. Only a non-finite sum (or float64 input) needs the exact test."""
    if not cube.flags.c_contiguous:  # a Fortran-order upload: the plain test
        return bool(np.isfinite(cube).all())
    real = cube.view(cube.real.dtype) if np.iscomplexobj(cube) else cube
    if real.dtype.itemsize < 8 and np.isfinite(real.sum(dtype=np.float64)):
        return True
    return bool(np.isfinite(real).all())


async def read_cube(chunks: AsyncIterator[bytes], expected: ExpectedCube, *, content_length: int | None) -> np.ndarray:
    """The cube of a .npy body stream, checked: header first, then the bytes, then finiteness.

    Raises ApiError 400 (not .npy, pickled, truncated or padded) or 422 (dtype, shape, NaN/Inf).
    """
    head = bytearray()
    header: NpyHeader | None = None
    data: np.ndarray | None = None
    filled = 0
    async for chunk in chunks:
        if not chunk:
            continue
        if header is None:
            head += chunk
            needed = _header_length(head)
            if needed is None or len(head) < needed:
                continue
            try:
                header = parse_npy_header(bytes(head[:needed]))
            except DataError as exc:
                raise ApiError(400, str(exc), error="malformed_npy") from None
            check_header(header, expected, content_length)
            data = np.empty(header.nbytes, np.uint8)  # allocated only now that the header is known to fit
            chunk = bytes(head[header.data_offset:])
            head = bytearray()
        assert data is not None
        if filled + len(chunk) > data.size:
            raise ApiError(400, f"body holds more than the {data.size} data bytes its .npy header announces",
                           error="malformed_npy")
        data[filled:filled + len(chunk)] = np.frombuffer(chunk, np.uint8)
        filled += len(chunk)
    if header is None or data is None:
        raise ApiError(400, "body is empty or ends inside the .npy header", error="malformed_npy")
    if filled != data.size:
        raise ApiError(400, f"body ends after {filled} of the {data.size} data bytes its .npy header announces",
                       error="malformed_npy")
    cube = data.view(header.dtype).reshape(header.shape, order="F" if header.fortran_order else "C")
    if not _all_finite(cube):
        raise ApiError(422, f"cube contains NaN or Inf values: model {expected.model!r} expects finite values",
                       error="invalid_cube")
    if not cube.dtype.isnative:
        cube = cube.astype(cube.dtype.newbyteorder("="))
    return cube
