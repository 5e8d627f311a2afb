"""Safe .npy decoding: the header is parsed and checked (dtype, shape, byte count) before any
allocation, object dtypes (pickles) are refused, and values can be checked for NaN/Inf.

Used by the readers and by the HTTP service for uploaded cubes.
"""

from __future__ import annotations

import ast
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radar.errors import DataError

MAGIC = b"\x93NUMPY"
# numpy's own default bound (``np.load(max_header_size=10000)``); real headers are about 120 bytes.
MAX_HEADER_LEN = 10000
# A plain header is a dict holding a shape tuple (depth 2); 4 leaves room and refuses what would make
# ``ast.literal_eval`` recurse (4,000 nested brackets raise RecursionError, 60,000 unary minus signs MemoryError).
MAX_HEADER_NESTING = 4
MAX_UNARY_RUN = 2


@dataclass(frozen=True)
class NpyHeader:
    dtype: np.dtype
    shape: tuple[int, ...]
    fortran_order: bool
    data_offset: int  # byte offset of the array data

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize


def parse_npy_header(head: bytes, *, source: str | Path | None = None) -> NpyHeader:
    """Parse the header at the start of ``head`` (the first few hundred bytes suffice).

    Raises DataError for a missing magic string, an unsupported version, an unreadable header
    dict, or an object dtype (a pickle would be needed to read it, and we never unpickle).
    """
    if len(head) < 10 or not head.startswith(MAGIC):
        raise DataError(source, "not a .npy file (missing the \\x93NUMPY magic string)")
    major = head[6]
    if major == 1:
        header_len, start = int.from_bytes(head[8:10], "little"), 10
    elif major in (2, 3):
        if len(head) < 12:
            raise DataError(source, "truncated .npy header")
        header_len, start = int.from_bytes(head[8:12], "little"), 12
    else:
        raise DataError(source, f"unsupported .npy format version {major}")
    if header_len > MAX_HEADER_LEN:
        raise DataError(source, f"oversized .npy header: {header_len} bytes, at most {MAX_HEADER_LEN} accepted")
    if len(head) < start + header_len:
        raise DataError(source, f"truncated .npy header: {len(head) - start} of its {header_len} bytes")
    text = head[start:start + header_len].decode("latin1")
    _check_literal_bounds(text, source)
    try:
        meta = ast.literal_eval(text)
        descr, fortran, shape = meta["descr"], meta["fortran_order"], meta["shape"]
        dtype = np.dtype(descr) if isinstance(descr, str) else None
    except (ValueError, SyntaxError, KeyError, TypeError) as exc:
        raise DataError(source, f"malformed .npy header ({exc})") from None
    if dtype is None or dtype.hasobject or dtype.fields is not None:
        raise DataError(source, f"refusing .npy with dtype {descr!r}: only plain numeric dtypes are accepted "
                                "(object arrays would need pickle)")
    if not (isinstance(shape, tuple) and all(isinstance(s, int) and s >= 0 for s in shape)):
        raise DataError(source, f"malformed .npy shape {shape!r}")
    return NpyHeader(dtype, shape, bool(fortran), start + header_len)


def _check_literal_bounds(text: str, source: str | Path | None) -> None:
    """Refuse a header literal nested deeper than MAX_HEADER_NESTING brackets, or with a run of more than
    MAX_UNARY_RUN unary signs, before ``ast.literal_eval`` sees it (its parser recurses on both)."""
    depth = deepest = run = longest = 0
    for char in text:
        if char in "([{":
            depth += 1
            deepest = max(deepest, depth)
        elif char in ")]}":
            depth -= 1
        run = run + 1 if char in "+-~" else (run if char.isspace() else 0)
        longest = max(longest, run)
    if deepest > MAX_HEADER_NESTING:
        raise DataError(source, f"malformed .npy header: brackets nested {deepest} deep, at most "
                                f"{MAX_HEADER_NESTING} expected")
    if longest > MAX_UNARY_RUN:
        raise DataError(source, f"malformed .npy header: a run of {longest} sign characters, at most "
                                f"{MAX_UNARY_RUN} expected")


def check_array(array: np.ndarray, *, source: str | Path | None, shape: tuple[int, ...] | None = None,
                dtypes: tuple[type, ...] | None = None, finite: bool = True, what: str = "array") -> np.ndarray:
    """Check an array's shape, dtype kind and finiteness; raise DataError saying what was expected."""
    if shape is not None and tuple(array.shape) != tuple(shape):
        raise DataError(source, f"{what} has shape {tuple(array.shape)}, expected {tuple(shape)}")
    if dtypes is not None and not any(np.issubdtype(array.dtype, d) for d in dtypes):
        names = ", ".join(np.dtype(d).name if d not in (np.floating, np.complexfloating, np.integer)
                          else d.__name__ for d in dtypes)
        raise DataError(source, f"{what} has dtype {array.dtype}, expected one of: {names}")
    if finite and np.issubdtype(array.dtype, np.inexact) and not np.isfinite(array).all():
        raise DataError(source, f"{what} contains NaN or Inf values")
    return array


def decode_npy(payload: bytes, *, shape: tuple[int, ...] | None = None, dtypes: tuple[type, ...] | None = None,
               finite: bool = True, source: str | Path | None = None) -> np.ndarray:
    """Decode a whole .npy payload held in memory, checking the header before allocating."""
    header = parse_npy_header(payload[:MAX_HEADER_LEN + 12], source=source)
    if shape is not None and header.shape != tuple(shape):
        raise DataError(source, f"array has shape {header.shape}, expected {tuple(shape)}")
    if len(payload) - header.data_offset != header.nbytes:
        raise DataError(source, f"array data is {len(payload) - header.data_offset} bytes, the header "
                                f"{header.shape} {header.dtype} needs {header.nbytes}")
    array = np.load(io.BytesIO(payload), allow_pickle=False)
    return check_array(array, source=source, shape=shape, dtypes=dtypes, finite=finite)


def read_npy_header(path: str | Path, *, what: str = "array") -> NpyHeader:
    """The checked header of a .npy file (its first bytes only: check the shape before reading the data)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, f"missing file (expected the {what})")
    with path.open("rb") as fh:
        return parse_npy_header(fh.read(MAX_HEADER_LEN + 12), source=path)


def load_npy(path: str | Path, *, shape: tuple[int, ...] | None = None, dtypes: tuple[type, ...] | None = None,
             finite: bool = True, what: str = "array") -> np.ndarray:
    """Load a .npy file after checking its header, size, dtype, shape and values."""
    path = Path(path)
    header = read_npy_header(path, what=what)
    if shape is not None and header.shape != tuple(shape):
        raise DataError(path, f"{what} has shape {header.shape}, expected {tuple(shape)}")
    size = path.stat().st_size
    if size - header.data_offset != header.nbytes:
        raise DataError(path, f"truncated or padded file: {size - header.data_offset} data bytes, "
                              f"{header.shape} {header.dtype} needs {header.nbytes}")
    array = np.load(path, allow_pickle=False)
    return check_array(array, source=path, shape=shape, dtypes=dtypes, finite=finite, what=what)
