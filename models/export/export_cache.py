"""The export cache: ONNX exports of checkpoint pairs (float, or int8 with its calibration) made on first use and
kept under ``RADARSEG_ONNX_CACHE`` (default ``~/.cache/radarseg/onnx``), keyed by what they depend on, and the ONNX
engine built on them (:func:`onnx_erasenet`). Above both the float export (:mod:`models.export.onnx_export`) and
the int8 one (:mod:`models.export.quantize`, which runs the float engine to calibrate), so no import goes round.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.cache_secret import cache_secret
from models.checkpoint import Checkpoint
from models.environment import environment
from models.export import quantize
from models.export.onnx_engine import OnnxEraseNet
from models.export.onnx_export import FORMAT, VERSION, checkpoint_digest, export_onnx
from models.export.quantize import (
    QUANT_VERSION,
    calibration_digest,
    export_int8,
)
from radar.profiles import RadarProfile

log = logging.getLogger(__name__)

CACHE_ENV = "RADARSEG_ONNX_CACHE"
KEY_FILE_ENV = "RADARSEG_ONNX_CACHE_KEY_FILE"  # this machine's secret that seals its exports (default below)


def _file_digests(directory: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir())
            if p.is_file() and p.name != "manifest.json"}


def _seal_mac(key: str, files: dict[str, str], secret: bytes) -> str:
    return hmac.new(secret, json.dumps({"key": key, "files": files}, sort_keys=True).encode(), "sha256").hexdigest()


def seal(directory: Path, key: str, secret: bytes) -> None:
    """Write into the export's manifest the sha256 of each of its files, what built it (``key``: the checkpoints'
    digests, format and recipe) and a MAC of both under this machine's secret."""
    manifest = json.loads((directory / "manifest.json").read_text())
    files = _file_digests(directory)
    manifest["seal"] = {"key": key, "files": files, "mac": _seal_mac(key, files, secret)}
    tmp = directory / ".manifest.json.tmp"
    tmp.write_text(json.dumps(manifest, indent=2))
    os.replace(tmp, directory / "manifest.json")


def seal_problem(directory: Path, key: str, secret: bytes) -> str | None:
    """Why the cached export in ``directory`` cannot be used (None when it can): no seal, sealed for other
    checkpoints or another machine, or a file whose content is not the one sealed."""
    try:
        stated = json.loads((directory / "manifest.json").read_text()).get("seal")
    except (OSError, ValueError) as exc:
        return f"unreadable manifest ({type(exc).__name__})"
    if not isinstance(stated, dict) or not isinstance(stated.get("files"), dict):
        return "no content hashes in its manifest"
    if stated.get("key") != key:
        return "built from other checkpoints or another recipe"
    if not hmac.compare_digest(str(stated.get("mac")), _seal_mac(key, stated["files"], secret)):
        return "not sealed by this machine's cache key"
    actual = _file_digests(directory)
    if changed := sorted(name for name in set(actual) | set(stated["files"])
                         if actual.get(name) != stated["files"].get(name)):
        return f"content differs from its manifest's hashes: {', '.join(changed)}"
    return None


def cache_root() -> Path:
    """Where exports are cached: ``$RADARSEG_ONNX_CACHE``, else ``~/.cache/radarseg/onnx``."""
    return environment().onnx_cache or Path.home() / ".cache" / "radarseg" / "onnx"


def exported_dir(detector: Checkpoint, segmenter: Checkpoint,
                 root: Path | None = None, *, int8: Int8Calibration | None = None) -> Path:
    """The export of this checkpoint pair, made now if the cache does not hold it yet.

    The directory is named by a MAC, under this machine's :func:`cache_secret`, of the sha256 of both checkpoints
    and the export format version, and for an int8 export (``int8`` given) also of the quantisation recipe's version
    and the sha256 of the calibration frames; its manifest seals the content of every file (:func:`seal`), checked
    at each load: an export whose files changed, or that this machine did not seal, is exported again;
    a new export is written to a temporary directory and renamed into place, so concurrent processes (Ray
    actors) never read half a directory: the first rename wins and the others use its files.
    """
    root = cache_root() if root is None else root
    digests = (checkpoint_digest(detector), checkpoint_digest(segmenter))
    name = f"{FORMAT}/{VERSION}/{digests[0]}/{digests[1]}"
    if int8 is not None:
        name += (f"/int8/{QUANT_VERSION}/{calibration_digest(int8.cubes)}/{','.join(int8.methods)}/"
                 f"{json.dumps(int8.pipeline)}")
    secret = cache_secret()
    target = root / hmac.new(secret, name.encode(), "sha256").hexdigest()[:24]
    if (target / "manifest.json").is_file():
        if (problem := seal_problem(target, name, secret)) is None:
            return target
        log.warning("cached ONNX export %s not used (%s): exporting it again", target, problem)
        rejected = root / f".rejected-{target.name}-{os.getpid()}"
        try:
            os.rename(target, rejected)
        except OSError:
            pass
        shutil.rmtree(rejected, ignore_errors=True)
    float_dir = None if int8 is None else exported_dir(detector, segmenter, root)
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".export-", dir=root))
    try:
        log.info("exporting the checkpoints to ONNX%s into %s", "" if int8 is None else " (int8)", target)
        if int8 is None:
            export_onnx(detector, segmenter, staging)
        else:
            export_int8(detector, segmenter, staging, cubes=int8.cubes, calibration=int8.description,
                        methods=int8.methods, float_dir=float_dir, pipeline=dict(int8.pipeline))
        seal(staging, name, secret)
        try:
            os.rename(staging, target)
        except OSError:  # another process renamed its export first
            if not (target / "manifest.json").is_file():
                raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return target


@dataclass(frozen=True)
class Int8Calibration:
    """What an int8 export calibrates on: log-power frames (R, A, D) dB, their description for the manifest, and
    the calibration methods to choose from (:mod:`models.export.quantize`)."""

    cubes: tuple[np.ndarray, ...]
    description: dict[str, Any]
    methods: tuple[str, ...]
    pipeline: tuple[tuple[str, Any], ...] = ()
    """EraseNet keyword arguments of the float pipeline whose ROI the segmenter is calibrated on (the served
    model's ``score_threshold`` and ``max_objects``); empty: EraseNet's defaults."""

    def with_pipeline(self, **kwargs: Any) -> Int8Calibration:
        return Int8Calibration(self.cubes, self.description, self.methods, tuple(sorted(kwargs.items())))

    @classmethod
    def simulated(cls, profile: RadarProfile, *, frames: int | None = None,
                  methods: tuple[str, ...] | None = None) -> Int8Calibration:
        """Simulated frames of ``profile`` (the default when no store is given; see :mod:`models.export.quantize`)."""
        # read when called (a test may lower them): quantize's defaults
        frames = quantize.CALIBRATION_FRAMES if frames is None else frames
        cubes, description = quantize.simulated_calibration_frames(profile, frames)
        return cls(tuple(cubes), description, tuple(quantize.METHODS if methods is None else methods))


def onnx_erasenet(detector: Checkpoint, segmenter: Checkpoint, *, int8: bool = False,
                  calibration: Int8Calibration | None = None, onnx_dir: str | Path | None = None,
                  **kwargs: Any) -> OnnxEraseNet:
    """The ONNX engine on the cached export of these checkpoints (exported now if never before), or on the export
    in ``onnx_dir``. ``int8``: the quantised graphs, calibrated on ``calibration`` (default:
    :meth:`Int8Calibration.simulated` frames of the checkpoints' preset) and on the ROI this model's own seeds give
    (``score_threshold``, ``max_objects``)."""
    if onnx_dir is not None:
        return OnnxEraseNet.from_checkpoints(detector, segmenter, onnx_dir=onnx_dir, int8=int8, **kwargs)
    if int8:
        calibration = calibration or Int8Calibration.simulated(detector.profile)
        seeds = {k: kwargs[k] for k in ("score_threshold", "max_objects") if k in kwargs}
        calibration = calibration.with_pipeline(**seeds)
    onnx_dir = exported_dir(detector, segmenter, int8=calibration if int8 else None)
    return OnnxEraseNet.from_checkpoints(detector, segmenter, onnx_dir=onnx_dir, int8=int8, **kwargs)
