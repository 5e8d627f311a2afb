"""Compact encodings of integer arrays in JSON responses: run-length or zlib + base64 (both lossless)."""

from __future__ import annotations

import base64
import zlib

import numpy as np

from service.schemas import EncodedArray, MaskEncoding


def encode_array(array: np.ndarray, encoding: MaskEncoding) -> EncodedArray:
    """Encode an integer array (C order). ``rle``: (value, length) runs; ``zlib``: base64 of zlib(level 1)."""
    array = np.ascontiguousarray(array)
    if encoding is MaskEncoding.zlib:
        data = base64.b64encode(zlib.compress(array.tobytes(), 1)).decode("ascii")
        return EncodedArray(encoding=encoding, dtype=array.dtype.name, shape=list(array.shape), data=data)
    flat = array.ravel()
    if flat.size == 0:
        runs: list[tuple[int, int]] = []
    else:
        starts = np.flatnonzero(np.concatenate(([True], flat[1:] != flat[:-1])))
        lengths = np.diff(np.append(starts, flat.size))
        runs = list(zip(flat[starts].tolist(), lengths.tolist(), strict=True))
    return EncodedArray(encoding=encoding, dtype=array.dtype.name, shape=list(array.shape), runs=runs)


def decode_array(encoded: EncodedArray | dict) -> np.ndarray:
    """Inverse of :func:`encode_array` (for clients and tests)."""
    if isinstance(encoded, dict):
        encoded = EncodedArray.model_validate(encoded)
    dtype = np.dtype(encoded.dtype)
    if encoded.encoding is MaskEncoding.zlib:
        raw = zlib.decompress(base64.b64decode(encoded.data or ""))
        return np.frombuffer(raw, dtype).reshape(encoded.shape).copy()
    runs = np.asarray(encoded.runs or [], dtype=np.int64).reshape(-1, 2)
    return np.repeat(runs[:, 0], runs[:, 1]).astype(dtype).reshape(encoded.shape)
