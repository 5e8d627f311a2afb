"""A zarr v3 store cut into shards along its frame axis: what the preprocessed store (:mod:`pipelines.datasets.store`)
and the predictions store (:mod:`pipelines.inference.predictions_store`) share.

Every array holds one entry per frame slot (``N`` slots) and is cut at the same shard boundaries
(``S`` slots a shard). Volume arrays (one value per RAD voxel, RA cell, ...) use zarr's sharding
codec, one inner chunk per frame; the small per-frame arrays are plain chunks of one shard's frames.
The worker that owns shard ``i`` writes whole shard files (or whole chunks) and nothing else:
concurrent writes into one shard would lose data. Its progress marker ``progress/shard_NNNNN`` (a
group whose attributes hold the shard's summary) is written atomically after all of its arrays, and
the root attribute ``complete`` only after every shard and the final attributes: an interrupted job
leaves no marker for a half-written shard and no ``complete`` store. Encoding (:func:`compressor_for`): zstd level 1;
floating-point arrays through Blosc's byte shuffle first (a ``carrada`` frame's float16 log power: 4.7 MB instead
of 6.0 MB without the shuffle, of 8.4 MB raw, and faster to write; docs/reference/data.md).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import zarr
from zarr.codecs import BloscCodec, ZstdCodec

from radar.errors import DataError, UserError

log = logging.getLogger(__name__)

PROGRESS = "progress"
ZSTD_LEVEL = 1


class Sharded:
    """Shard arithmetic and buffers of a layout with ``n_frames`` slots in shards of ``shard_frames`` and at
    most ``max_objects`` objects per frame (mixed into the frozen layout dataclasses of both stores).

    A layout names its arrays in ``arrays()`` (``name -> (per-frame shape, dtype, fill value)``), its
    volume arrays in ``VOLUME_ARRAYS`` and its identity in ``to_dict()``.
    """

    VOLUME_ARRAYS: ClassVar[tuple[str, ...]] = ()
    n_frames: int
    shard_frames: int
    max_objects: int

    def __post_init__(self) -> None:
        if self.n_frames < 1 or self.shard_frames < 1 or self.max_objects < 1:
            raise ValueError(f"n_frames, shard_frames and max_objects must be >= 1, got {self.n_frames}, "
                             f"{self.shard_frames}, {self.max_objects}")

    def arrays(self) -> dict[str, tuple[tuple[int, ...], str, Any]]:
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        raise NotImplementedError

    @property
    def n_shards(self) -> int:
        return -(-self.n_frames // self.shard_frames)

    def shard_bounds(self, shard: int) -> tuple[int, int]:
        """Frame slots ``[start, stop)`` of shard ``shard``."""
        if not 0 <= shard < self.n_shards:
            raise ValueError(f"shard {shard} out of range [0, {self.n_shards})")
        start = shard * self.shard_frames
        return start, min(start + self.shard_frames, self.n_frames)

    def empty_shard(self, shard: int) -> dict[str, np.ndarray]:
        """Buffers of every array for shard ``shard``, at their fill values."""
        start, stop = self.shard_bounds(shard)
        return {name: np.full((stop - start, *shape), fill, dtype=dtype)
                for name, (shape, dtype, fill) in self.arrays().items()}


# --------------------------------------------------------------------------- before any work
def check_resumable_out(out: Path, *, store_format: str, identity: Any, what: str) -> None:
    """An existing ``--out`` must be empty, or a store of ``store_format`` written by a job with the same
    ``identity`` (which is then resumed); anything else is refused before any work starts."""
    if not out.exists():
        return
    if not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    meta = out / "zarr.json"
    if not meta.is_file():
        if any(out.iterdir()):
            raise UserError(f"--out {out} exists and is not a {what}; choose another path")
        return
    try:
        attrs = json.loads(meta.read_text()).get("attributes", {})
    except json.JSONDecodeError as exc:
        raise DataError(meta, f"not valid JSON ({exc})") from None
    if attrs.get("format") != store_format:
        raise UserError(f"--out {out} is a zarr store but not a {what}; choose another path")
    if attrs.get("plan") != identity:
        raise UserError(f"--out {out} holds a {what} written with other arguments (it can only be resumed "
                         f"with the same ones); choose another path or remove it")


# --------------------------------------------------------------------------- writing
def compressor_for(dtype: str) -> BloscCodec | ZstdCodec:
    """The codec of an array of ``dtype``: floats byte-shuffled (their exponent bytes, alike from value to value,
    then sit together and compress) before zstd; integers (labels, counts: long runs already) plain zstd."""
    kind = np.dtype(dtype)
    if kind.kind == "f":
        return BloscCodec(cname="zstd", clevel=ZSTD_LEVEL, shuffle="shuffle", typesize=kind.itemsize)
    return ZstdCodec(level=ZSTD_LEVEL)


def create_sharded_store(path: str | Path, layout: Sharded, attributes: dict[str, Any], *, store_format: str,
                         version: int) -> zarr.Group:
    """Create the group, every (empty) array and the progress group; ``complete`` starts False."""
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    for name, (shape, dtype, fill) in layout.arrays().items():
        if name in layout.VOLUME_ARRAYS:
            chunks, shards = (1, *shape), (layout.shard_frames, *shape)
        else:
            chunks, shards = (layout.shard_frames, *shape), None
        root.create_array(name, shape=(layout.n_frames, *shape), dtype=dtype, chunks=chunks, shards=shards,
                          compressors=compressor_for(dtype), fill_value=fill)
    root.create_group(PROGRESS)
    root.attrs.update({**attributes, "format": store_format, "version": version, "layout": layout.to_dict(),
                       "complete": False})
    return root


def write_shard_arrays(path: str | Path, layout: Sharded, shard: int, buffers: dict[str, np.ndarray]) -> None:
    """Write the whole of shard ``shard`` of every array from ``buffers`` (see :meth:`Sharded.empty_shard`)."""
    start, stop = layout.shard_bounds(shard)
    # One worker = one core: Ray gives each task or actor one CPU, so zarr's codec pool stays at one thread.
    with zarr.config.set({"threading.max_workers": 1}):
        root = zarr.open_group(str(path), mode="r+")
        for name in layout.arrays():
            root[name][start:stop] = buffers[name]


def finish_store(path: str | Path, attributes: dict[str, Any]) -> None:
    """Write the store's final attributes, then (a separate, last write) ``complete = True``."""
    root = zarr.open_group(str(path), mode="r+")
    root.attrs.update({**attributes, "complete": False})
    root.attrs.update({"complete": True})


def _marker_dir(path: str | Path, shard: int) -> Path:
    return Path(path) / PROGRESS / f"shard_{shard:05d}"


def mark_shard_done(path: str | Path, shard: int, summary: dict[str, Any]) -> None:
    """Write shard ``shard``'s progress marker, a zarr v3 group whose attributes hold ``summary``.

    The metadata file is written to a temporary name and renamed, so a marker is either absent or
    complete; it is the last thing a shard's worker writes.
    """
    marker = _marker_dir(path, shard)
    marker.mkdir(parents=True, exist_ok=True)
    payload = json.dumps({"zarr_format": 3, "node_type": "group", "attributes": summary}, allow_nan=False)
    tmp = marker / ".zarr.json.tmp"
    tmp.write_text(payload)
    os.replace(tmp, marker / "zarr.json")


def done_shards(path: str | Path) -> dict[int, dict[str, Any]]:
    """Summaries of the shards whose markers exist, by shard number (unreadable markers count as not done)."""
    done: dict[int, dict[str, Any]] = {}
    progress = Path(path) / PROGRESS
    if not progress.is_dir():
        return done
    for marker in sorted(progress.glob("shard_*/zarr.json")):
        try:
            shard = int(marker.parent.name.removeprefix("shard_"))
            done[shard] = json.loads(marker.read_text())["attributes"]
        except (ValueError, KeyError, json.JSONDecodeError) as exc:
            log.warning("ignoring unreadable progress marker %s (%s)", marker, exc)
    return done


# --------------------------------------------------------------------------- reading
def open_sharded_store(path: str | Path, *, store_format: str, version: int, require_complete: bool,
                       what: str, writer: str) -> zarr.Group:
    """Open a store read-only; DataError when it is not a (finished) store of ``store_format``.

    ``what`` names the store in messages ("store"), ``writer`` the job that writes it ("preprocessing job").
    """
    path = Path(path)
    if not (path / "zarr.json").is_file():
        hint = (f"; it is a recording: preprocess it first (radarseg preprocess --source recording:{path} --out "
                f"STORE.zarr)" if (path / "recording.json").is_file() else "")
        raise DataError(path, f"not a zarr store (missing zarr.json){hint}")
    root = zarr.open_group(str(path), mode="r")
    attrs = root.attrs.asdict()
    if attrs.get("format") != store_format:
        raise DataError(path, f"expected a store with format {store_format!r}, found {attrs.get('format')!r}")
    if attrs.get("version") != version:
        raise DataError(path, f"unsupported {what} version {attrs.get('version')!r}, expected {version}")
    if require_complete and not attrs.get("complete"):
        raise DataError(path, f"{what} is incomplete (its {writer} was interrupted; rerun it to resume)")
    return root
