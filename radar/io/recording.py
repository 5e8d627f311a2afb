"""The radarseg recording layout: simulated (or converted) sequences on disk.

::

    DIR/
      recording.json             format, version, preset, radar parameters, classes, sequences, source,
                                 simulator (version and options of the simulator that made it, or null)
      seq_000/
        cubes/000000.npy         complex64 (R, A, D) RAD cube in the project's frame (docs/design.md section 2)
        adc/000000.npy           (ADC recordings, content "adc", instead of cubes) complex64 raw samples
                                 (samples, chirps, virtual elements); processed into the cube on read
                                 by radar.adc.process_adc: 10-30x smaller than the cubes
        labels/000000.npz        compressed: labels uint8 (R, A, D) classes, instances uint8 (R, A, D)
        objects.json             {"frames": [[object, ...], ...]}: one object table per frame

Every file is written to a temporary name and renamed, and ``recording.json`` is written last, so an
interrupted write leaves no file that looks complete and no recording that looks finished.
"""

from __future__ import annotations

import json
import os
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from radar.adc import adc_shape, process_adc, ti_to_sck
from radar.adc_checks import AdcCheckError
from radar.errors import DataError
from radar.frame import ObjectRecord, RadarFrame
from radar.io.npy import check_array, load_npy
from radar.profiles import RadarProfile, UnknownPresetError, resolve_profile
from radar.profiles.files import ProfileError, profile_to_dict
from radar.schema import SchemaMismatch, check_schema, cube_schema
from radar.ti.recorded_capture import CaptureAppender, RecordedCaptures

FORMAT = "radarseg.recording"
VERSION = 1


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    with tmp.open("wb") as fh:
        write(fh)
    os.replace(tmp, path)


def _frame_name(index: int) -> str:
    return f"{index:06d}"


class RecordingWriter:
    """Writes frames sequence by sequence; ``close()`` (or the context manager) writes recording.json."""

    def __init__(self, out_dir: str | Path, profile: RadarProfile, *, source: dict[str, Any] | None = None,
                 content: str = "cube", adc_format: str = "npy"):
        """``content``: ``"cube"`` writes RAD cubes; ``"adc"`` writes the raw ADC samples instead (frames
        must carry ``extras["adc"]``, as simulated frames do)."""
        if content not in ("cube", "adc"):
            raise ValueError(f"content must be 'cube' or 'adc', got {content!r}")
        self.content = content
        # adc_format "dca1000": one DCA1000 capture per sequence instead of a .npy per frame (radar/ti/recorded_capture)
        self.capture = CaptureAppender(profile) if content == "adc" and adc_format == "dca1000" else None
        self.tdm_compensation = False  # ADC recordings: whether the samples carry TDM coupling to remove
        self.tdm_coupling = False
        self.simulator: dict[str, Any] | None = None  # version and options of the simulator that made the frames
        self.root = Path(out_dir)
        if (self.root / "recording.json").exists():
            raise FileExistsError(f"{self.root}: a recording already exists here; choose another --out")
        self.root.mkdir(parents=True, exist_ok=True)
        self.profile = profile
        self.source = source or {}
        self.sequences: dict[str, int] = {}
        self._objects: dict[str, list[list[dict]]] = {}

    def write(self, frame: RadarFrame) -> None:
        if frame.cube.shape != self.profile.shape:
            raise ValueError(f"frame cube {frame.cube.shape} does not match profile {self.profile.shape}")
        seq_dir = self.root / frame.sequence
        (seq_dir / ("adc" if self.content == "adc" else "cubes")).mkdir(parents=True, exist_ok=True)
        (seq_dir / "labels").mkdir(exist_ok=True)
        name = _frame_name(frame.index)
        if "simulator" in frame.extras:
            if self.simulator is not None and frame.extras["simulator"] != self.simulator:
                raise ValueError(f"{frame.sequence}/{frame.index}: made by simulator {frame.extras['simulator']}, "
                                 f"the recording's earlier frames by {self.simulator}")
            self.simulator = frame.extras["simulator"]
        if self.content == "adc":
            if "adc" not in frame.extras:
                raise ValueError(f"{frame.sequence}/{frame.index}: an ADC recording needs frames that carry their ADC")
            self.tdm_compensation = bool(frame.extras.get("tdm_compensation", False))
            self.tdm_coupling = bool(frame.extras.get("tdm_coupling", False))
            if self.capture is not None:
                self.capture.append(seq_dir, frame.extras["adc"], frame.index)
            else:
                _atomic_write(seq_dir / "adc" / f"{name}.npy",
                              lambda fh: np.save(fh, frame.extras["adc"], allow_pickle=False))
        else:
            _atomic_write(seq_dir / "cubes" / f"{name}.npy", lambda fh: np.save(fh, frame.cube, allow_pickle=False))
        if frame.labels is not None:
            _atomic_write(seq_dir / "labels" / f"{name}.npz",
                          lambda fh: np.savez_compressed(fh, labels=frame.labels, instances=frame.instances))
        tables = self._objects.setdefault(frame.sequence, [])
        if frame.index != len(tables):
            raise ValueError(f"{frame.sequence}: frames must be written in order; got {frame.index} "
                             f"after {len(tables)} frames")
        tables.append([o.to_dict() for o in frame.objects])
        self.sequences[frame.sequence] = len(tables)
        # Object tables are rewritten per frame so that a sequence is readable up to the last frame.
        payload = json.dumps({"frames": tables}).encode()
        _atomic_write(seq_dir / "objects.json", lambda fh: fh.write(payload))

    def close(self) -> Path:
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "preset": self.profile.name,
            "radar_file": profile_to_dict(self.profile) if self.profile.chirp is not None else None,
            "schema": cube_schema(self.profile),
            "content": self.content,
            "tdm_coupling": self.tdm_coupling,
            "tdm_compensation": self.tdm_compensation,
            "simulator": self.simulator,
            "radar": self.profile.to_dict(),
            "classes": list(self.profile.all_class_names),
            "sequences": dict(sorted(self.sequences.items())),
            "source": self.source,
            **(self.capture.meta() if self.capture is not None else {}),
        }
        payload = json.dumps(meta, indent=2).encode()
        _atomic_write(self.root / "recording.json", lambda fh: fh.write(payload))
        return self.root

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:  # an interrupted write leaves no recording.json behind
            self.close()


class Recording:
    """Reader of a recording directory. Frames come back as :class:`RadarFrame`, checked on load."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        meta_path = self.root / "recording.json"
        if not self.root.is_dir():
            raise DataError(self.root, "no such recording directory")
        if not meta_path.is_file():
            raise DataError(meta_path, "missing recording.json (not a radarseg recording, or its "
                                       "writing was interrupted)")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise DataError(meta_path, f"not valid JSON ({exc})") from None
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise DataError(meta_path, f"expected a JSON object with format {FORMAT!r}")
        if meta.get("version") != VERSION:
            raise DataError(meta_path, f"unsupported recording version {meta.get('version')!r}, expected {VERSION}")
        try:
            self.profile = resolve_profile(meta.get("preset"), meta.get("radar_file"), source=str(meta_path))
        except (ProfileError, UnknownPresetError) as exc:
            raise DataError(meta_path, str(exc)) from None
        if "schema" in meta:  # cubes written for another radar (or an older profile) are refused here
            try:
                check_schema(cube_schema(self.profile), meta["schema"], what="recording")
            except SchemaMismatch as exc:
                raise DataError(meta_path, str(exc)) from None
        sequences = meta.get("sequences")
        if not isinstance(sequences, dict) or not all(isinstance(n, int) and n >= 0 for n in sequences.values()):
            raise DataError(meta_path, "expected 'sequences' to map sequence names to frame counts")
        self.content = meta.get("content", "cube")
        if self.content not in ("cube", "adc"):
            raise DataError(meta_path, f"content {self.content!r}, expected 'cube' or 'adc'")
        self.meta = meta
        self._captures = (RecordedCaptures(self.root, self.profile, meta, meta_path)
                          if self.content == "adc" and meta.get("adc_format") == "dca1000" else None)
        self._sequences: dict[str, int] = sequences
        self._objects: dict[str, list[list[dict]]] = {}

    def sequences(self) -> list[str]:
        return list(self._sequences)

    def n_frames(self, sequence: str) -> int:
        self._check_sequence(sequence)
        return self._sequences[sequence]

    def __len__(self) -> int:
        return sum(self._sequences.values())

    def split(self, sequence: str) -> str | None:
        """Recordings carry no split; the preprocessing job assigns one by sequence."""
        return None

    def _check_sequence(self, sequence: str) -> None:
        if sequence not in self._sequences:
            raise DataError(self.root, f"unknown sequence {sequence!r}; recording has {self.sequences()}")

    def _object_tables(self, sequence: str) -> list[list[dict]]:
        if sequence not in self._objects:
            path = self.root / sequence / "objects.json"
            if not path.is_file():
                raise DataError(path, "missing file (expected the sequence's object tables)")
            try:
                frames = json.loads(path.read_text())["frames"]
            except (json.JSONDecodeError, KeyError, TypeError, UnicodeDecodeError) as exc:
                raise DataError(path, f"expected JSON {{'frames': [[object, ...], ...]}} ({exc!r})") from None
            if len(frames) < self._sequences[sequence]:
                raise DataError(path, f"holds {len(frames)} frames, recording.json says {self._sequences[sequence]}")
            self._objects[sequence] = frames
        return self._objects[sequence]

    def read_frame(self, sequence: str, index: int) -> RadarFrame:
        self._check_sequence(sequence)
        if not 0 <= index < self._sequences[sequence]:
            raise DataError(self.root / sequence, f"frame {index} out of range [0, {self._sequences[sequence]})")
        name = _frame_name(index)
        seq_dir = self.root / sequence
        if self.content == "adc":
            if self._captures is not None:  # the sequence's DCA1000 capture
                adc = ti_to_sck(self._captures.frame(sequence, index), self.profile)
            else:
                adc = load_npy(seq_dir / "adc" / f"{name}.npy", shape=adc_shape(self.profile),
                               dtypes=(np.complexfloating,), what="ADC samples (samples, chirps, virtual elements)")
            try:  # undecoded words refused naming the file (radar.adc_checks)
                cube = process_adc(adc, self.profile, tdm_compensation=bool(self.meta.get("tdm_compensation", False)))
            except AdcCheckError as exc:
                raise DataError(seq_dir / "adc" / f"{name}.npy", str(exc)) from None
        else:
            cube = load_npy(seq_dir / "cubes" / f"{name}.npy", shape=self.profile.shape,
                            dtypes=(np.complexfloating, np.floating), what="RAD cube")
        labels_path = seq_dir / "labels" / f"{name}.npz"
        if not labels_path.is_file():
            raise DataError(labels_path, "missing file (expected the frame's labels and instances)")
        try:
            with np.load(labels_path, allow_pickle=False) as npz:
                labels, instances = npz["labels"], npz["instances"]
        except (KeyError, ValueError, OSError, zipfile.BadZipFile) as exc:
            raise DataError(labels_path, f"expected a .npz with arrays 'labels' and 'instances' ({exc})") from None
        for arr, what in ((labels, "labels"), (instances, "instances")):
            check_array(arr, source=labels_path, shape=self.profile.shape, dtypes=(np.uint8,), what=what)
        if labels.max(initial=0) >= self.profile.num_classes:
            raise DataError(labels_path, f"labels hold class {labels.max()}, expected < {self.profile.num_classes}")
        try:
            objects = tuple(ObjectRecord.from_dict(o) for o in self._object_tables(sequence)[index])
        except (TypeError, ValueError) as exc:
            raise DataError(seq_dir / "objects.json", f"frame {index}: bad object record ({exc})") from None
        return RadarFrame(cube=cube, profile=self.profile, sequence=sequence, index=index, labels=labels,
                          instances=instances, objects=objects)

    def frames(self, sequence: str | None = None) -> Iterator[RadarFrame]:
        """Frames of one sequence, or of all sequences in order."""
        for seq in [sequence] if sequence is not None else self.sequences():
            for index in range(self.n_frames(seq)):
                yield self.read_frame(seq, index)
