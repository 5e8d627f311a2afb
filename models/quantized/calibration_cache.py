"""The int8 segmenter's calibration kept on disk: a start of an int8 model reads its ranges back (well under a
second) instead of calibrating again (~20 s of simulated frames through the float pipeline).

One JSON file per calibration under ``RADARSEG_INT8_CACHE`` (default ``~/.cache/radarseg/int8``), named by the
sha256 of its key: everything the ranges depend on (:func:`calibration_key`: both checkpoints' sha256, the
calibration frames' settings or content hash, the float pipeline's seed settings, the method, the source of
``radar/`` and ``models/`` and the numpy and torch versions). The file repeats its key and is sealed as the ONNX
exports are: an HMAC-SHA256 of key and ranges under this user's secret (:mod:`models.cache_secret`, outside every
cache), so whoever can write the folder cannot make a file this machine will use (a plain sha256 let scales x 1e4 be
used). A file larger than :data:`MAX_FILE_BYTES` is not read; one whose key differs (stale), whose seal does not
match, that does not parse, or whose ranges do not fit the network (any error at all) is never used: :func:`load`
says why and the caller calibrates again and writes it anew (atomically: a temporary file renamed into place, so a
concurrent reader never sees half a file).
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import json
import logging
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from models.cache_secret import cache_secret
from models.environment import environment
from models.quantized.segmenter import InputRange, Int8MinkUNet, padded
from models.segmenter.fused import FusedMinkUNet

log = logging.getLogger(__name__)

FORMAT = "radarseg-int8-calibration"
VERSION = 2  # 2: sealed with an HMAC under this user's cache secret (1: a plain sha256)
MAX_FILE_BYTES = 4 << 20  # a calibration is a few hundred scales; a larger file is not read
SOURCE_PACKAGES = ("radar", "models")
"""Packages whose source the ranges depend on (the simulator, region growing, the detector, the fused segmenter)."""


def cache_root() -> Path:
    """Where calibrations are kept: ``$RADARSEG_INT8_CACHE``, else ``~/.cache/radarseg/int8``."""
    return environment().int8_cache or Path.home() / ".cache" / "radarseg" / "int8"


@functools.lru_cache(maxsize=1)
def source_digest() -> str:
    """sha256 of the Python source of :data:`SOURCE_PACKAGES` (path and bytes of each file, in path order)."""
    root = Path(__file__).resolve().parents[2]
    digest = hashlib.sha256()
    for package in SOURCE_PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            digest.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def calibration_key(*, detector_sha256: str, segmenter_sha256: str, frames: dict[str, Any], pipeline: dict[str, Any],
                    method: str, per_channel: bool = False) -> dict[str, Any]:
    """What a calibration depends on, as JSON values. ``frames``: the calibration frames' settings (simulated) or
    their description and content hash (a store's); ``pipeline``: the float pipeline's settings that choose the ROI
    (score threshold, objects a frame, region growing, Doppler refinement). Returned as JSON reads it back (tuples
    as lists, other values as text), so a key compares equal to the one a file holds."""
    key = {"format": FORMAT, "version": VERSION, "detector_sha256": detector_sha256,
           "segmenter_sha256": segmenter_sha256, "frames": frames, "pipeline": pipeline, "method": method,
           "per_channel": per_channel, "source_sha256": source_digest(), "numpy": np.__version__,
           "torch": torch.__version__}
    return json.loads(json.dumps(key, default=str))


def _canonical(value: Any) -> bytes:
    return json.dumps(value, sort_keys=True, separators=(",", ":")).encode()


def cache_path(key: dict[str, Any], root: Path | None = None) -> Path:
    """The file of the calibration with ``key``."""
    return (cache_root() if root is None else root) / f"{hashlib.sha256(_canonical(key)).hexdigest()[:32]}.json"


def _ranges(int8: Int8MinkUNet) -> dict[str, Any]:
    return {"input_low": int8.input_range.low.float().tolist(), "input_high": int8.input_range.high.float().tolist(),
            "activation_scales": [s.float().tolist() for s in int8.activation_scales]}


def _seal(key: dict[str, Any], ranges: dict[str, Any]) -> str:
    return hmac.new(cache_secret(), _canonical({"key": key, "ranges": ranges}), "sha256").hexdigest()


def save(path: Path, key: dict[str, Any], int8: Int8MinkUNet) -> None:
    """Write ``int8``'s calibrated ranges with ``key`` and their seal to ``path`` (float32 values written exactly)."""
    ranges = _ranges(int8)
    record = {"key": key, "ranges": ranges, "mac": _seal(key, ranges)}
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".calibration-", suffix=".json", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as out:
            json.dump(record, out)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(path: Path, key: dict[str, Any], fused: FusedMinkUNet) -> tuple[Int8MinkUNet | None, str | None]:
    """The int8 network of ``fused`` with the ranges in ``path``, or (None, why not): no file, a file larger than
    :data:`MAX_FILE_BYTES` (not read), one of another key (stale), one this machine did not seal, or one that cannot
    be read or does not fit the network (corrupt). Any error at all is a reason, never an exception."""
    try:
        if not path.is_file():
            return None, "none kept"
        if (size := path.stat().st_size) > MAX_FILE_BYTES:
            return None, f"corrupt: {size} bytes, a calibration is at most {MAX_FILE_BYTES} (not read)"
        with path.open("rb") as source:
            record = json.loads(source.read(MAX_FILE_BYTES + 1))
        stated, ranges = record["key"], record["ranges"]
        if not hmac.compare_digest(str(record.get("mac")), _seal(stated, ranges)):
            return None, "corrupt: not sealed by this machine's cache key"
        if stated != key:
            changed = sorted(name for name in set(key) | set(stated) if key.get(name) != stated.get(name))
            return None, f"stale: calibrated for another {', '.join(changed)}"
        return _network(fused, ranges), None
    except Exception as exc:  # noqa: BLE001 (whatever is wrong with a kept file, the answer is to calibrate again)
        return None, f"corrupt: unreadable ({type(exc).__name__}: {str(exc)[:200]})"


class _Widths:
    """A layer runner that walks the network (:meth:`FusedMinkUNet.walk`) computing nothing: each activation's
    output channels, in the order the int8 network takes their scales."""

    def __init__(self) -> None:
        self.widths: list[int] = []

    def _submanifold(self, x: None, conv: Any, state: None, residual: None = None) -> None:
        self.widths.append(int(conv.weight.shape[2]))

    _strided = _transposed = _submanifold

    def _residual(self, x: None, block: Any, state: None) -> None:
        self._submanifold(x, block.first, state)
        self._submanifold(x, block.second, state)

    def _concat(self, up: None, skip: None) -> None:
        return None


def _network(fused: FusedMinkUNet, ranges: dict[str, Any]) -> Int8MinkUNet:
    """The int8 network with ``ranges``; ValueError unless there is one scale vector per activation of the network,
    each at most its padded width (a list of the wrong length raised IndexError in the first frame)."""
    walk = _Widths()
    fused.walk(None, walk, None)
    scales = [torch.tensor(s, dtype=torch.float32).reshape(-1) for s in ranges["activation_scales"]]
    if len(scales) != len(walk.widths) or any(not 1 <= len(s) <= padded(w) for s, w in zip(scales, walk.widths,
                                                                                            strict=False)):
        raise ValueError(f"{len(scales)} activation scale vectors of lengths {[len(s) for s in scales][:8]}..., the "
                         f"network has {len(walk.widths)} activations of widths {walk.widths[:8]}...")
    input_range = InputRange(torch.tensor(ranges["input_low"], dtype=torch.float32),
                             torch.tensor(ranges["input_high"], dtype=torch.float32))
    return Int8MinkUNet(fused, input_range, scales)
