"""The preprocessed store (docs/design.md section 4): zarr v3 schema, frame encoding, reader, torch Dataset.

Layout of ``STORE.zarr`` (one zarr v3 group; ``N`` frame slots, ``S`` frames per shard)::

    input      float16 (N, R, A, D)   log power 10*log10(|I|^2 + 1) in dB        sharded (S, R, A, D), chunk 1 frame
    labels     uint8   (N, R, A, D)   class cube, 0 = background                  sharded likewise
    instances  uint8   (N, R, A, D)   instance cube; ids index the object table   sharded likewise
    ra_mask    uint8   (N, R, A)      RA projection of ``labels``                  sharded, chunk 1 frame
    rd_mask    uint8   (N, R, D)      RD projection of ``labels``                  sharded, chunk 1 frame
    heatmap    float16 (N, R/4, A/4)  centre heatmap (docs/design.md section 5 Gaussian)    sharded, chunk 1 frame
    objects    float32 (N, K, F)      object table, NaN padded (columns OBJECT_FIELDS)   chunk S frames
    n_objects  int32   (N,)           rows of ``objects`` in use                  chunk S frames
    frame_index int32  (N,)           frame index within its sequence             chunk S frames
    sequence_id int32  (N,)           index into the ``sequences`` attribute       chunk S frames
    split      uint8   (N,)           0 train, 1 val, 2 test (SPLITS)             chunk S frames
    valid      uint8   (N,)           1 written, 0 quarantined (data left at the fill value)
    progress/shard_NNNNN              a zarr group per finished shard (attributes: the shard's summary)

Every array is cut along the frame axis at the same shard boundaries (``S`` frames); the Ray task that
owns a shard writes it whole, then its progress marker, and ``complete`` comes last (the mechanics of
both of our stores: :mod:`pipelines.datasets.sharded_store`).

Objects with no labelled voxel (``n_voxels == 0``) are not in the table: they are not targets.
Encoding: zstd level 1, floats byte-shuffled first (:func:`pipelines.datasets.sharded_store.compressor_for`).
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import zarr

from models.detector.targets import OUTPUT_STRIDE, output_grid, render_heatmap
from pipelines.datasets.history import earlier_slots
from pipelines.datasets.sharded_store import Sharded, create_sharded_store, done_shards, open_sharded_store
from radar import transforms
from radar.centres import MAX_OBJECTS
from radar.errors import DataError
from radar.frame import RadarFrame
from radar.io.npy import check_array
from radar.profiles import RadarProfile, resolve_profile

log = logging.getLogger(__name__)

FORMAT = "radarseg.store"
VERSION = 1
SPLITS = ("train", "val", "test")
SPLIT_CODE = {name: code for code, name in enumerate(SPLITS)}
NO_SPLIT = 255
OBJECT_FIELDS = ("instance_id", "class_id", "range_bin", "angle_bin", "doppler_bin",
                 "offset_range", "offset_angle", "x", "y", "n_voxels", "track_id", "vx", "vy")
"""Columns of the object table. The last three (the simulator's track id and velocity vector, m/s; NaN from
data sets without them) are the truth for tracking; a store made before them has the first ten."""
TRACKING_FIELDS = ("track_id", "vx", "vy")
OBJECT_COLUMN = {name: i for i, name in enumerate(OBJECT_FIELDS)}  # column of each field in ``objects``
CENTRE_COLUMNS = [OBJECT_COLUMN["range_bin"], OBJECT_COLUMN["angle_bin"], OBJECT_COLUMN["doppler_bin"]]

# Arrays holding one value per RAD voxel, RA cell, ... (sharded, one inner chunk per frame) and the
# small per-frame table arrays (plain chunks of one shard's frames).
VOLUME_ARRAYS = ("input", "labels", "instances", "ra_mask", "rd_mask", "heatmap")
TABLE_ARRAYS = ("objects", "n_objects", "frame_index", "sequence_id", "split", "valid")
FRAME_ARRAYS = VOLUME_ARRAYS + ("objects", "n_objects")  # what encode_frame produces


@dataclass(frozen=True)
class StoreLayout(Sharded):
    """Shapes, dtypes and shard boundaries of a store of ``n_frames`` slots of one radar profile."""

    VOLUME_ARRAYS: ClassVar[tuple[str, ...]] = VOLUME_ARRAYS
    profile: RadarProfile
    n_frames: int
    shard_frames: int
    max_objects: int = MAX_OBJECTS
    output_stride: int = OUTPUT_STRIDE

    @property
    def heatmap_shape(self) -> tuple[int, int]:
        return output_grid((self.profile.n_range, self.profile.n_angle), self.output_stride)

    def arrays(self) -> dict[str, tuple[tuple[int, ...], str, Any]]:
        """``name -> (per-frame shape, dtype, fill value)``."""
        R, A, D = self.profile.shape
        return {
            "input": ((R, A, D), "float16", 0.0),
            "labels": ((R, A, D), "uint8", 0),
            "instances": ((R, A, D), "uint8", 0),
            "ra_mask": ((R, A), "uint8", 0),
            "rd_mask": ((R, D), "uint8", 0),
            "heatmap": (self.heatmap_shape, "float16", 0.0),
            "objects": ((self.max_objects, len(OBJECT_FIELDS)), "float32", float("nan")),
            "n_objects": ((), "int32", 0),
            "frame_index": ((), "int32", -1),
            "sequence_id": ((), "int32", -1),
            "split": ((), "uint8", NO_SPLIT),
            "valid": ((), "uint8", 0),
        }

    def to_dict(self) -> dict[str, Any]:
        return {"preset": self.profile.name, "n_frames": self.n_frames, "shard_frames": self.shard_frames,
                "max_objects": self.max_objects, "output_stride": self.output_stride}


# --------------------------------------------------------------------------- writing
def create_store(path: str | Path, layout: StoreLayout, attributes: dict[str, Any]) -> zarr.Group:
    """Create an empty store (``complete`` False until the preprocessing job finishes it)."""
    return create_sharded_store(path, layout, attributes, store_format=FORMAT, version=VERSION)


def encode_frame(frame: RadarFrame, layout: StoreLayout) -> dict[str, np.ndarray]:
    """One frame's arrays as stored (per-frame shapes of :meth:`StoreLayout.arrays`).

    Raises DataError when the cube or labels are of the wrong shape or dtype or not finite, and
    ValueError when the frame holds more labelled objects than the table's width.
    """
    profile = layout.profile
    source = f"{frame.sequence}/{frame.index}"
    check_array(frame.cube, source=source, shape=profile.shape, dtypes=(np.complexfloating, np.floating),
                what="RAD cube")
    if frame.labels is None or frame.instances is None:
        raise DataError(source, "frame carries no labels; the store needs labelled frames")
    for arr, what in ((frame.labels, "labels"), (frame.instances, "instances")):
        check_array(arr, source=source, shape=profile.shape, dtypes=(np.uint8,), what=what)
    log_power = transforms.log_power(frame.cube)
    if not np.isfinite(log_power).all() or log_power.max() >= np.finfo(np.float16).max:
        raise DataError(source, "log power is not finite in float16")
    objects = [o for o in frame.objects if o.n_voxels > 0]  # objects without voxels are no targets
    if len(objects) > layout.max_objects:
        raise ValueError(f"{source}: {len(objects)} labelled objects, more than the table's {layout.max_objects}")
    table = np.full((layout.max_objects, len(OBJECT_FIELDS)), np.nan, np.float32)
    centres = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in objects],
                       np.float64).reshape(-1, 3)
    scaled = centres[:, :2] / layout.output_stride
    offsets = scaled - np.floor(scaled)
    for k, o in enumerate(objects):
        table[k] = (o.instance_id, o.class_id, o.centre_range_bin, o.centre_angle_bin, o.doppler_bin,
                    offsets[k, 0], offsets[k, 1], o.centre_x, o.centre_y, o.n_voxels,
                    o.track_id if o.track_id >= 0 else np.nan, o.true_vx, o.true_vy)
    heatmap = render_heatmap(centres, (profile.n_range, profile.n_angle), output_stride=layout.output_stride)
    return {
        "input": log_power.astype(np.float16),
        "labels": frame.labels,
        "instances": frame.instances,
        "ra_mask": frame.ra_mask(),
        "rd_mask": frame.rd_mask(),
        "heatmap": heatmap.astype(np.float16),
        "objects": table,
        "n_objects": np.int32(len(objects)),
    }


# --------------------------------------------------------------------------- reading
def store_profile(attrs: dict, path: str | Path) -> RadarProfile:
    """The radar of a store from its attributes: a built-in preset by name, or the file form it keeps."""
    return resolve_profile(attrs["preset"], attrs.get("radar_file"), source=f"store {path}")


def open_store(path: str | Path, *, require_complete: bool = True) -> zarr.Group:
    """Open a store read-only; raise DataError when it is not a (finished) radarseg store."""
    return open_sharded_store(path, store_format=FORMAT, version=VERSION, require_complete=require_complete,
                              what="store", writer="preprocessing job")


def tracking_truth_problem(root: zarr.Group, path: str | Path) -> str | None:
    """Why the store cannot be the truth for tracking, in one line (None when it can): a store made before
    the object table had its track id and velocity columns, or one whose source has no track ids."""
    width = root["objects"].shape[-1]
    if width < len(OBJECT_FIELDS):
        return (f"store {path} predates tracking truth (object table of {width} columns, not {len(OBJECT_FIELDS)}):"
                f" run radarseg preprocess again to get track ids and velocities")
    return None


def frames_of_split(root: zarr.Group, split: str | None) -> np.ndarray:
    """Frame slots (int64, ascending) of the valid frames of ``split`` (None = every split)."""
    valid = root["valid"][:].astype(bool)
    if split is None:
        return np.flatnonzero(valid)
    if split not in SPLIT_CODE:
        raise ValueError(f"split must be one of {', '.join(SPLITS)} (or all), got {split!r}")
    return np.flatnonzero(valid & (root["split"][:] == SPLIT_CODE[split]))


def flip_angle(sample: dict[str, Any], profile: RadarProfile, *, output_stride: int = OUTPUT_STRIDE,
               doppler_last: bool = False) -> dict[str, Any]:
    """Mirror a sample left-right (x -> -x), in place of a copy; range and Doppler never flip.

    Angle bin ``a`` (``sin(theta) = (a - A/2)/(A/2)``) mirrors to ``(A - a) mod A``: bin A/2
    (broadside) stays, bin 0 (endfire, sin = -1) maps to itself as it has no +1 partner. Fractional
    centres map to ``A - a``, ``x`` to ``-x``; sub-cell offsets and the heatmap are recomputed from
    the mirrored centres (flipping the stored heatmap would be off by a cell, as floor() is not
    symmetric). Array axes: ``input`` (D, R, A), or (R, A, D) with ``doppler_last``, ``history`` (H, D, R, A),
    ``labels``/``instances`` (R, A, D), ``ra_mask`` (R, A).
    """
    n_angle = profile.n_angle
    out = dict(sample)

    def mirror(t: torch.Tensor, axis: int) -> torch.Tensor:
        """``t[(A - a) mod A]`` along ``axis``: bin 0 kept, bins 1.. reversed (one numpy copy; torch.flip and
        torch.roll took 10x longer on a cube)."""
        a = t.numpy()
        first, rest = [slice(None)] * a.ndim, [slice(None)] * a.ndim
        first[axis], rest[axis] = slice(0, 1), slice(None, 0, -1)
        return torch.from_numpy(np.concatenate([a[tuple(first)], a[tuple(rest)]], axis=axis))

    for name, axis in (("input", 1 if doppler_last else 2), ("history", 3), ("labels", 1), ("instances", 1),
                       ("ra_mask", 1)):
        if name in sample:
            out[name] = mirror(sample[name], axis)
    if "objects" in sample:
        table = sample["objects"].clone()
        n = int(sample["n_objects"])
        angle = n_angle - table[:n, OBJECT_COLUMN["angle_bin"]].double()
        table[:n, OBJECT_COLUMN["angle_bin"]] = angle.float()
        table[:n, OBJECT_COLUMN["x"]] = -table[:n, OBJECT_COLUMN["x"]]
        if table.shape[-1] > OBJECT_COLUMN["vx"]:  # a store made before tracking truth has no velocity
            table[:n, OBJECT_COLUMN["vx"]] = -table[:n, OBJECT_COLUMN["vx"]]
        table[:n, OBJECT_COLUMN["offset_angle"]] = (angle / output_stride - torch.floor(angle / output_stride)).float()
        out["objects"] = table
        if "heatmap" in sample:
            centres = table[:n, CENTRE_COLUMNS].double().numpy()
            heatmap = render_heatmap(centres, (profile.n_range, n_angle), output_stride=output_stride)
            out["heatmap"] = torch.from_numpy(heatmap)[None]
    return out


class StoreDataset(torch.utils.data.Dataset):
    """Frames of one split of a store, as torch tensors, for training.

    A sample is a dict with (depending on ``fields``):

    - ``input``: float32 (D, R, A), Doppler as channels (docs/design.md section 5); log power in dB, or
      ``(x - mean_d) / std_d`` with the store's train-split statistics per Doppler bin when ``normalise``;
    - ``labels``, ``instances``: uint8 (R, A, D); ``ra_mask`` uint8 (R, A); ``rd_mask`` uint8 (R, D);
    - ``heatmap``: float32 (1, R/4, A/4);
    - ``objects``: float32 (K, F) NaN-padded table (columns ``OBJECT_FIELDS``: bins, cells, metres);
      ``n_objects``: int64 scalar; always present together;
    - ``frame``: int, the store slot; ``flipped``: bool;
    - with ``history`` H > 0 (and ``input`` among the fields): ``history`` float32 (H, D, R, A), the sequence's
      earlier frames scaled as ``input`` (the latest first, zero where absent), and ``history_present`` bool (H,)
      (:mod:`pipelines.datasets.history`); ``history_drop`` > 0 drops a sample's whole history at random
      (reproducibly from ``seed`` and the slot), so that a model trained on it also runs on a single cube.

    ``doppler_last``: ``input`` float32 (R, A, D) as stored, never normalised (what region growing reads; no
    transposition, which dominated a ``carrada`` ROI sample's time).

    ``flip_prob`` > 0 mirrors samples left-right at random (:func:`flip_angle`), reproducibly from
    ``seed`` and the sample index. Arrays are opened lazily in each process (zarr's I/O thread does
    not survive a fork), so the dataset works in DataLoader workers.
    """

    ALL_FIELDS = ("input", "labels", "instances", "ra_mask", "rd_mask", "heatmap", "objects")

    def __init__(self, path: str | Path, split: str | None = "train", *, fields: Sequence[str] = ALL_FIELDS,
                 normalise: bool = True, flip_prob: float = 0.0, seed: int = 0, history: int = 0,
                 history_drop: float = 0.0, doppler_last: bool = False):
        unknown = set(fields) - set(self.ALL_FIELDS)
        if unknown:
            raise ValueError(f"unknown fields {sorted(unknown)}; expected a subset of {self.ALL_FIELDS}")
        if not 0.0 <= flip_prob <= 1.0:
            raise ValueError(f"flip_prob must be in [0, 1], got {flip_prob}")
        if not 0.0 <= history_drop <= 1.0:
            raise ValueError(f"history_drop must be in [0, 1], got {history_drop}")
        if history and "input" not in fields:
            raise ValueError("history needs the 'input' field")
        if doppler_last and (normalise or history):
            raise ValueError("doppler_last gives the stored (R, A, D) log power: not normalised, without history")
        self.path = Path(path)
        root = open_store(self.path)
        attrs = root.attrs.asdict()
        self.profile = store_profile(attrs, self.path)
        self.output_stride = int(attrs["layout"]["output_stride"])
        self.frames = frames_of_split(root, split)
        self.split = split
        self.fields = tuple(fields)
        self.normalise = normalise
        self.flip_prob = flip_prob
        self.seed = seed
        self.history = earlier_slots(root, history) if history else None
        self.history_drop = history_drop
        self.doppler_last = doppler_last
        stats = attrs["normalisation"]
        self.mean = torch.tensor(stats["mean_per_doppler"], dtype=torch.float32)[:, None, None]  # (D, 1, 1)
        self.std = torch.tensor(stats["std_per_doppler"], dtype=torch.float32)[:, None, None]
        self._arrays: dict[str, zarr.Array] | None = None
        self._pid = -1

    def __len__(self) -> int:
        return len(self.frames)

    def _open(self) -> dict[str, zarr.Array | np.ndarray]:
        if self._arrays is None or self._pid != os.getpid():
            root = zarr.open_group(str(self.path), mode="r")
            # the object table always comes along: flips recompute the heatmap from it
            names = list(dict.fromkeys([*self.fields, "objects", "n_objects"]))
            self._arrays = {name: root[name] for name in names}
            # the object table is small (a few KB per frame): read whole once, not through zarr per sample
            # (each read waits on zarr's I/O thread, about 4 ms; two of a detector sample's three reads)
            for name in ("objects", "n_objects"):
                self._arrays[name] = self._arrays[name][:]
            self._pid = os.getpid()
        return self._arrays

    def __getitem__(self, item: int) -> dict[str, Any]:
        if not 0 <= item < len(self.frames):
            raise IndexError(f"index {item} out of range for {len(self.frames)} frames")
        slot = int(self.frames[item])
        arrays = self._open()
        sample: dict[str, Any] = {"frame": slot, "flipped": False}
        for name, array in arrays.items():
            value = array[slot].copy() if isinstance(array, np.ndarray) else array[slot]  # never a view of the cache
            if name == "input":
                sample[name] = self._input(value)
            elif name == "heatmap":
                sample[name] = torch.from_numpy(value.astype(np.float32))[None]
            elif name == "n_objects":
                sample[name] = torch.tensor(int(value), dtype=torch.int64)
            else:
                sample[name] = torch.from_numpy(np.ascontiguousarray(value))
        if self.history is not None:
            self._add_history(sample, slot, arrays["input"])
        if self.flip_prob > 0:
            rng = np.random.default_rng([self.seed, slot])
            if rng.random() < self.flip_prob:
                sample = flip_angle(sample, self.profile, output_stride=self.output_stride,
                                    doppler_last=self.doppler_last)
                sample["flipped"] = True
        return sample

    def _input(self, value: np.ndarray) -> torch.Tensor:
        """A stored (R, A, D) log-power cube as the model's (D, R, A) float32, normalised if asked (or as it is
        stored, in float32, with ``doppler_last``)."""
        if self.doppler_last:
            return torch.from_numpy(value.astype(np.float32))
        tensor = torch.from_numpy(np.ascontiguousarray(value.astype(np.float32).transpose(2, 0, 1)))
        return (tensor - self.mean) / self.std if self.normalise else tensor

    def _add_history(self, sample: dict[str, Any], slot: int, inputs: zarr.Array) -> None:
        earlier = self.history[slot]
        dropped = self.history_drop > 0 and np.random.default_rng([self.seed, slot, 1]).random() < self.history_drop
        present = torch.from_numpy((earlier >= 0) & (not dropped))
        frames = [self._input(inputs[int(s)]) if ok else torch.zeros_like(sample["input"])
                  for s, ok in zip(earlier, present.tolist(), strict=True)]
        sample["history"] = torch.stack(frames)
        sample["history_present"] = present


# --------------------------------------------------------------------------- summary
def summarise(path: str | Path) -> dict[str, Any]:
    """Frames per split, class voxel counts, normalisation statistics and quarantined frames of a store."""
    root = open_store(path, require_complete=False)
    attrs = root.attrs.asdict()
    split = root["split"][:]
    valid = root["valid"][:].astype(bool)
    frames = {name: int(np.sum(valid & (split == code))) for name, code in SPLIT_CODE.items()}
    stats = attrs.get("normalisation", {})
    report = attrs.get("report", {})
    return {
        "path": str(path),
        "complete": bool(attrs.get("complete")),
        "preset": attrs.get("preset"),
        "shape": attrs.get("radar", {}).get("shape"),
        "classes": attrs.get("class_names"),
        "slots": int(len(valid)),
        "frames": frames,
        "class_voxel_counts": attrs.get("class_voxel_counts", {}),
        "normalisation": {"mean": stats.get("mean"), "std": stats.get("std"), "frames": stats.get("frames")},
        "quarantined": report.get("quarantined", []),
        "shards": attrs.get("layout", {}).get("shard_frames") and {
            "total": -(-int(len(valid)) // int(attrs["layout"]["shard_frames"])),
            "done": len(done_shards(path)),
        },
        "code_version": attrs.get("code_version"),
        "simulator": attrs.get("simulator"),
    }


def format_summary(summary: dict[str, Any]) -> str:
    """Human-readable lines of :func:`summarise`'s dict."""
    lines = [f"store {summary['path']}  ({'complete' if summary['complete'] else 'INCOMPLETE'})",
             f"  preset {summary['preset']}  cube {summary['shape']}  slots {summary['slots']}  "
             f"shards {summary['shards']['done']}/{summary['shards']['total']} done",
             "  frames: " + ", ".join(f"{k} {v}" for k, v in summary["frames"].items())]
    classes = summary["classes"] or []
    for split, counts in summary["class_voxel_counts"].items():
        lines.append(f"  voxels {split}: " + ", ".join(f"{c} {n}" for c, n in zip(classes, counts, strict=True)))
    norm = summary["normalisation"]
    if norm["mean"] is not None:
        lines.append(f"  input (train, {norm['frames']} frames): mean {norm['mean']:.3f} dB, std {norm['std']:.3f} dB")
    simulator = summary.get("simulator")
    if simulator:
        options = ", ".join(f"{k} {v}" for k, v in simulator["options"].items())
        lines.append(f"  simulator: version {simulator['version']} ({options})")
    else:
        lines.append("  simulator: none recorded (not simulated, or made before simulator versions were recorded)")
    lines.append(f"  quarantined: {len(summary['quarantined'])}")
    for q in summary["quarantined"]:
        lines.append(f"    {q['sequence']}/{q['index']} (slot {q['frame']}): {q['reason']}")
    return "\n".join(lines)


def array_checksums(path: str | Path, names: Iterable[str] | None = None) -> dict[str, str]:
    """sha256 of every array's decoded bytes (used to check that resumed and straight runs agree)."""
    root = zarr.open_group(str(path), mode="r")
    names = list(names) if names is not None else sorted(k for k, _ in root.arrays())
    return {name: hashlib.sha256(np.ascontiguousarray(root[name][:]).tobytes()).hexdigest() for name in names}
