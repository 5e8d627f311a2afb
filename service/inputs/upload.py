"""Reading an uploaded ``.npy`` cube from a request body stream.

The header is parsed and checked (dtype kind, shape, byte count against ``Content-Length``) as soon
as its bytes have arrived, before the array is allocated; the array is then filled chunk by chunk
(no second copy of a 32 MiB body). Pickled/object arrays are refused by the header parser.

Uploads are bounded before any model is involved: :class:`UploadGate` admits at most ``max_uploads``
bodies of at most ``max_upload_bytes`` together, and per tenant at most ``max_tenant_uploads`` of at most
``max_tenant_upload_bytes``, at once (503 + Retry-After beyond; so that one tenant's held uploads cannot take
every place), :func:`check_declared_length` refuses at once a declared length no cube of the model can have (413), and
:func:`paced` cuts off a body that falls behind ``body_min_rate`` bytes/s after ``body_grace_s`` seconds,
or is not complete within ``body_timeout_s`` (408, connection closed).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from radar.errors import DataError
from radar.input_kind import ACCEPTED_DTYPES, InputKindError, resolve_kind
from radar.input_kind import check_values as check_kind_values
from radar.io.npy import MAGIC, MAX_HEADER_LEN, NpyHeader, parse_npy_header
from service.http.errors import ApiError
from service.inputs.adc_upload import AdcFrameInput
from service.schemas import InputKind
from service.settings import Settings


@dataclass(frozen=True)
class ExpectedCube:
    """What a model accepts: its cube shape and the input kind the client announced; for ``?input=adc``, ``adc``:
    the ADC frame's layouts and sample types (service.inputs.adc_upload)."""

    model: str
    shape: tuple[int, int, int]
    kind: InputKind
    adc: AdcFrameInput | None = None

    def describe(self) -> str:
        if self.adc is not None:
            return self.adc.describe()
        names = "/".join(np.dtype(d).name for d in ACCEPTED_DTYPES[self.kind])
        return f"a {self.shape} {names} .npy cube"

    def max_body_bytes(self) -> int:
        """The largest .npy body of such a cube: the longest header accepted and the widest dtype."""
        widest = max(np.dtype(d).itemsize for d in ACCEPTED_DTYPES[self.kind])
        return 12 + MAX_HEADER_LEN + widest * int(np.prod(self.shape))


def check_declared_length(content_length: int | None, accepted: list[ExpectedCube]) -> None:
    """ApiError 413 at once for a declared length larger than any of the ``accepted`` cubes (every input kind of
    the model) can have."""
    largest = max(accepted, key=ExpectedCube.max_body_bytes)
    limit = largest.max_body_bytes()
    if content_length is not None and content_length > limit:
        raise ApiError(413, f"request body of {content_length} bytes is larger than any cube model {largest.model!r} "
                            f"takes: at most {limit} bytes ({largest.describe()} with ?input={largest.kind.value})",
                       headers={"Connection": "close"})


class UploadTicket:
    """One body's place in the gate: the bytes it is charged (its declared length, or for a chunked body its
    .npy header's size once that has arrived)."""

    def __init__(self, gate: UploadGate, tenant: str) -> None:
        self.gate = gate
        self.tenant = tenant
        self.bytes = 0

    def charge(self, total: int) -> None:
        """Charge the body ``total`` bytes (more than before); ApiError 503 when that passes a bound."""
        self.gate._grow(self, total - self.bytes)


class UploadGate:
    """Bounds the request bodies being received at once, in total and per tenant: their number and their bytes
    (what the cubes will occupy once allocated: the declared length, or for a chunked body the size its .npy
    header announces, charged as soon as the header has arrived and before the array is allocated)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.uploads = 0
        self.bytes = 0
        self.tenant_uploads: dict[str, int] = {}
        self.tenant_bytes: dict[str, int] = {}

    def _refuse(self, what: str) -> ApiError:
        return ApiError(503, f"{what}; try again later", error="uploads_saturated",
                        headers={"Retry-After": str(self.settings.retry_after_s)})

    def _grow(self, ticket: UploadTicket, extra: int) -> None:
        s, tenant = self.settings, ticket.tenant
        held = self.tenant_bytes.get(tenant, 0)
        if held + extra > s.max_tenant_upload_bytes:
            raise self._refuse(f"tenant {tenant!r} has uploads of {held} bytes in progress and this one needs "
                               f"{ticket.bytes + extra} (limit: {s.max_tenant_upload_bytes} bytes per tenant)")
        if self.bytes + extra > s.max_upload_bytes:
            raise self._refuse(f"uploads of {self.bytes} bytes are in progress and this one needs "
                               f"{ticket.bytes + extra} (limit: {s.max_upload_bytes} bytes)")
        ticket.bytes += extra
        self.bytes += extra
        self.tenant_bytes[tenant] = held + extra

    @contextmanager
    def admit(self, tenant: str, content_length: int | None) -> Iterator[UploadTicket]:
        """Hold a place for one body of ``tenant`` while it is read (charged ``content_length`` bytes at once when
        declared); ApiError 503 when a bound is reached."""
        s = self.settings
        if self.uploads >= s.max_uploads:
            raise self._refuse(f"{self.uploads} uploads in progress (limit: {s.max_uploads})")
        if self.tenant_uploads.get(tenant, 0) >= s.max_tenant_uploads:
            raise self._refuse(f"tenant {tenant!r} has {self.tenant_uploads[tenant]} uploads in progress (limit: "
                               f"{s.max_tenant_uploads} per tenant)")
        ticket = UploadTicket(self, tenant)
        if content_length:
            ticket.charge(content_length)
        self.uploads += 1
        self.tenant_uploads[tenant] = self.tenant_uploads.get(tenant, 0) + 1
        try:
            yield ticket
        finally:
            self.uploads -= 1
            self.bytes -= ticket.bytes
            self.tenant_uploads[tenant] -= 1
            self.tenant_bytes[tenant] = self.tenant_bytes.get(tenant, 0) - ticket.bytes
            if not self.tenant_uploads[tenant]:
                del self.tenant_uploads[tenant], self.tenant_bytes[tenant]


async def paced(chunks: AsyncIterator[bytes], settings: Settings) -> AsyncIterator[bytes]:
    """``chunks`` as they arrive, or ApiError 408 when the body falls behind ``body_min_rate`` after
    ``body_grace_s`` (the next bytes are due by ``start + grace + received / rate``), sends nothing for
    ``body_idle_s``, or is not complete within ``body_timeout_s``."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    deadline = start + settings.body_timeout_s
    received = 0
    last = start
    iterator = aiter(chunks)
    while True:
        idle_due = last + settings.body_idle_s
        due = min(deadline, idle_due, start + settings.body_grace_s + received / settings.body_min_rate)
        try:
            async with asyncio.timeout_at(due):
                chunk = await anext(iterator)
        except StopAsyncIteration:
            return
        except TimeoutError:
            elapsed = loop.time() - start
            why = (f"not complete within {settings.body_timeout_s:g} s" if due >= deadline else
                   f"silent for {settings.body_idle_s:g} s" if due >= idle_due else
                   f"below the minimum rate of {settings.body_min_rate} bytes/s after {settings.body_grace_s:g} s")
            raise ApiError(408, f"request body {why}: {received} bytes in {elapsed:.1f} s", error="body_timeout",
                           headers={"Connection": "close"}) from None
        received += len(chunk)
        last = loop.time()
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
    if expected.adc is not None:
        if expected.adc.layout_of(header) is None:
            raise ApiError(422, f"ADC frame has shape {header.shape} and dtype {header.dtype.name}, model "
                                f"{expected.model!r} expects {expected.describe()}", error="invalid_cube")
    elif header.dtype.newbyteorder("=") not in [np.dtype(d) for d in ACCEPTED_DTYPES[expected.kind]]:
        try:  # radar.input_kind's rule: a real-valued cube says what it holds
            resolve_kind(header.dtype, expected.kind, flag="?input={}")
            hint = ""
        except InputKindError as exc:
            hint = f" ({exc})"
        raise ApiError(422, f"cube has dtype {header.dtype.name}, model {expected.model!r} expects "
                            f"{expected.describe()}{hint}", error="invalid_cube")
    elif header.shape != expected.shape:
        axes = "(samples, chirps, virtual elements)" if expected.kind is InputKind.adc else "(range, angle, Doppler)"
        raise ApiError(422, f"cube has shape {header.shape}, model {expected.model!r} expects {expected.shape} "
                            f"{axes}", error="invalid_cube")
    total = header.data_offset + header.nbytes
    if content_length is not None and content_length != total:
        raise ApiError(400, f"body is {content_length} bytes but its .npy header ({header.shape} "
                            f"{header.dtype.name}) needs {total}", error="malformed_npy")


# The largest magnitude of a value (each of real and imaginary part) accepted per input kind: the transform runs in
# float32 (max 3.4e38), squares the values and sums the power of up to 256 angle bins (RD view), and a log-power cube
# is raised to 10**(dB/10); a finite value past these bounds would overflow to Inf there (3e38 or 1e300
# gave an empty answer, billed). ADC samples are bounded lower: the FFT chain adds up to ~4e6 of them per bin.
VALUE_BOUNDS = {InputKind.complex: 1e15, InputKind.magnitude: 1e15, InputKind.adc: 1e9, InputKind.log_power: 300.0}


def _largest_magnitude(cube: np.ndarray) -> float:
    """max |value| over real and imaginary parts, NaN when any value is NaN (Inf when any is infinite), in two
    passes (max and min) without a temporary the size of the cube."""
    parts = [cube.view(cube.real.dtype)] if np.iscomplexobj(cube) and cube.flags.c_contiguous else (
        [cube.real, cube.imag] if np.iscomplexobj(cube) else [cube])
    largest = 0.0
    for part in parts:
        high, low = float(part.max()), float(part.min())
        if np.isnan(high) or np.isnan(low):
            return float("nan")
        largest = max(largest, high, -low)
    return largest


def check_values(cube: np.ndarray, expected: ExpectedCube) -> None:
    """ApiError 422 for NaN/Inf, for values impossible for the declared kind (``radar.input_kind``), or for a
    finite value too large for the float32 transform (VALUE_BOUNDS)."""
    largest = _largest_magnitude(cube)
    if not np.isfinite(largest):
        raise ApiError(422, f"cube contains NaN or Inf values: model {expected.model!r} expects finite values",
                       error="invalid_cube")
    try:  # values impossible for the declared kind (linear magnitude as ?input=log_power, ...): radar.input_kind
        check_kind_values(cube, expected.kind, flag="?input={}")
    except InputKindError as exc:
        raise ApiError(422, f"model {expected.model!r}: {exc}", error="invalid_cube") from None
    bound = VALUE_BOUNDS[expected.kind]
    if largest > bound:
        what = "dB values" if expected.kind is InputKind.log_power else "real and imaginary parts"
        raise ApiError(422, f"cube holds a value of magnitude {largest:.3g}: model {expected.model!r} accepts {what} "
                            f"within [-{bound:g}, {bound:g}] (the float32 range of its transform)",
                       error="invalid_cube")


async def read_cube(chunks: AsyncIterator[bytes], expected: ExpectedCube, *, content_length: int | None,
                    ticket: UploadTicket | None = None) -> np.ndarray:
    """The cube of a .npy body stream, checked: header first, then the bytes, then finiteness. A chunked body
    (no ``content_length``) is charged to ``ticket`` the size its header announces before the array is allocated.

    Raises ApiError 400 (not .npy, pickled, truncated or padded) or 422 (dtype, shape, NaN/Inf, a value beyond
    VALUE_BOUNDS).
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
            if ticket is not None and content_length is None:
                ticket.charge(header.data_offset + header.nbytes)
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
    if expected.adc is not None:  # the model takes complex samples in the "sck" layout
        cube = expected.adc.to_sck(cube, expected.adc.layout_of(header))
    check_values(cube, expected)
    if not cube.dtype.isnative:
        cube = cube.astype(cube.dtype.newbyteorder("="))
    return cube
