"""Reader of the public CARRADA layout, converted to the project's RAD frame (docs/design.md section 3.2).

Layout read::

    ROOT/data_seq_ref.json                   {seq: {"split": "Train"|"Validation"|"Test", ...}}
    ROOT/annotations_frame_oriented.json     {seq: {frame: {instance: {"range_angle"|"range_doppler":
                                                 {"dense": [[row, col], ...], "box": ..., "label": c}}}}}
    ROOT/<seq>/RAD_numpy/000123.npy          (256, 256, 64) range x angle x Doppler, complex or magnitude
    ROOT/<seq>/annotations/dense/000123/range_angle.npy    (4, 256, 256) one-hot (bg, ped, cyclist, car)
    ROOT/<seq>/annotations/dense/000123/range_doppler.npy  (4, 256, 64) one-hot

Orientation, as read from CARRADA's own code, and how we convert (the one place this happens):

- RA annotations and the RAD cube store range descending (row 0 = far end; their code maps a range
  to row ``256 - r/res``): we flip the range axis, so our bin ``r`` is their row ``255 - r``. The RD
  annotations already store range ascending (row 0 = near) and are not flipped.
- Angle column 128 is 0 deg and columns grow with x (to the right), as ours do. CARRADA's annotation
  code spaces the columns uniformly in theta while the cube comes from an FFT (uniform in
  sin(theta)); we keep the columns as they are and read them as sin(theta) bins (the two agree to
  within a bin near broadside and drift apart towards +-90 deg).
- Doppler zero is at column 32 = D/2, positive velocities at higher columns, as ours.
- A real-valued RAD cube is taken as a magnitude; a complex one is kept as is (complex64).

CARRADA has no RAD labels. We derive them per instance as the voxels whose RA cell and RD cell both
carry that instance (its ``dense`` points in the frame-oriented annotations), and the class cube
from the dense one-hot masks the same way (RA class == RD class). This approximates the paper's
RAD labelling pipeline; where two instances claim a voxel the lower instance id keeps it.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from radar.errors import DataError
from radar.frame import ObjectRecord, RadarFrame
from radar.instances import instance_stats
from radar.io.npy import load_npy
from radar.profiles import CARRADA

SPLITS = {"Train": "train", "Validation": "val", "Test": "test"}


def _read_json(path: Path, what: str) -> Any:
    if not path.is_file():
        raise DataError(path, f"missing file (expected {what})")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(path, f"not valid JSON ({exc})") from None


def _mask_from_points(points: Any, shape: tuple[int, int], path: Path, what: str) -> np.ndarray:
    try:
        pts = np.asarray(points, dtype=np.int64).reshape(-1, 2)
    except (TypeError, ValueError):
        raise DataError(path, f"{what}: expected a list of [row, col] points") from None
    if len(pts) and ((pts < 0).any() or (pts[:, 0] >= shape[0]).any() or (pts[:, 1] >= shape[1]).any()):
        raise DataError(path, f"{what}: points outside the {shape} grid")
    mask = np.zeros(shape, bool)
    mask[pts[:, 0], pts[:, 1]] = True
    return mask


class CarradaReader:
    """Frames of a CARRADA root as :class:`RadarFrame` in the project's frame, checked on load."""

    profile = CARRADA

    def __init__(self, root: str | Path):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(self.root, "no such CARRADA root directory")
        seq_ref = _read_json(self.root / "data_seq_ref.json", "the sequence table data_seq_ref.json")
        if not isinstance(seq_ref, dict):
            raise DataError(self.root / "data_seq_ref.json", "expected an object {sequence: {split: ...}}")
        self._splits: dict[str, str] = {}
        for seq, info in seq_ref.items():
            split = info.get("split") if isinstance(info, dict) else None
            if split not in SPLITS:
                raise DataError(self.root / "data_seq_ref.json",
                                f"sequence {seq!r}: split {split!r}, expected one of {sorted(SPLITS)}")
            self._splits[seq] = SPLITS[split]
        self._annotations = _read_json(self.root / "annotations_frame_oriented.json",
                                       "the frame-oriented annotations annotations_frame_oriented.json")
        self._frames: dict[str, list[str]] = {}

    def sequences(self) -> list[str]:
        return sorted(self._splits)

    def split(self, sequence: str) -> str:
        """``train``, ``val`` or ``test`` from data_seq_ref.json."""
        self._check_sequence(sequence)
        return self._splits[sequence]

    def _check_sequence(self, sequence: str) -> None:
        if sequence not in self._splits:
            raise DataError(self.root, f"unknown sequence {sequence!r}; data_seq_ref.json lists {self.sequences()}")

    def frame_names(self, sequence: str) -> list[str]:
        self._check_sequence(sequence)
        if sequence not in self._frames:
            rad_dir = self.root / sequence / "RAD_numpy"
            if not rad_dir.is_dir():
                raise DataError(rad_dir, "missing directory (expected the sequence's RAD cubes)")
            self._frames[sequence] = sorted(p.stem for p in rad_dir.glob("*.npy"))
        return self._frames[sequence]

    def n_frames(self, sequence: str) -> int:
        return len(self.frame_names(sequence))

    def __len__(self) -> int:
        return sum(self.n_frames(s) for s in self.sequences())

    def read_frame(self, sequence: str, index: int) -> RadarFrame:
        names = self.frame_names(sequence)
        if not 0 <= index < len(names):
            raise DataError(self.root / sequence, f"frame {index} out of range [0, {len(names)})")
        name = names[index]
        seq_dir = self.root / sequence
        R, A, D = CARRADA.shape
        cube = load_npy(seq_dir / "RAD_numpy" / f"{name}.npy", shape=(R, A, D),
                        dtypes=(np.complexfloating, np.floating), what="RAD cube")
        cube = cube.astype(np.complex64 if np.iscomplexobj(cube) else np.float32, copy=False)
        cube = np.ascontiguousarray(cube[::-1])  # range descending -> ascending

        dense_dir = seq_dir / "annotations" / "dense" / name
        ra_onehot = load_npy(dense_dir / "range_angle.npy", shape=(4, R, A), what="RA one-hot mask")
        rd_onehot = load_npy(dense_dir / "range_doppler.npy", shape=(4, R, D), what="RD one-hot mask")
        ra_class = ra_onehot.argmax(axis=0)[::-1]  # (R, A), flipped to range ascending
        rd_class = rd_onehot.argmax(axis=0)  # (R, D)
        labels = np.where(ra_class[:, :, None] == rd_class[:, None, :], ra_class[:, :, None], 0).astype(np.uint8)

        instances = np.zeros(CARRADA.shape, np.uint8)
        class_ids: list[int] = []
        frame_ann = self._annotations.get(sequence, {}).get(name, {}) if isinstance(self._annotations, dict) else {}
        ann_path = self.root / "annotations_frame_oriented.json"
        for inst_key in sorted(frame_ann, key=str):
            inst = frame_ann[inst_key]
            try:
                ra_ann, rd_ann = inst["range_angle"], inst["range_doppler"]
                label = int(ra_ann["label"])
                ra_points, rd_points = ra_ann["dense"], rd_ann["dense"]
            except (KeyError, TypeError, ValueError):
                raise DataError(ann_path, f"{sequence}/{name}/{inst_key}: expected range_angle and range_doppler "
                                          "entries with 'dense' points and a 'label'") from None
            if not 1 <= label < CARRADA.num_classes:
                raise DataError(ann_path, f"{sequence}/{name}/{inst_key}: label {label} outside 1..3")
            ra_mask = _mask_from_points(ra_points, (R, A), ann_path, f"{sequence}/{name}/{inst_key} RA")[::-1]
            rd_mask = _mask_from_points(rd_points, (R, D), ann_path, f"{sequence}/{name}/{inst_key} RD")
            voxels = ra_mask[:, :, None] & rd_mask[:, None, :] & (instances == 0)
            class_ids.append(label)
            instances[voxels] = len(class_ids)
        stats = instance_stats(instances, CARRADA, n_instances=len(class_ids))
        objects = tuple(
            ObjectRecord(
                instance_id=i, class_id=c, class_name=CARRADA.class_names[c - 1], n_voxels=int(stats.n_voxels[i]),
                centre_x=float(stats.x[i]), centre_y=float(stats.y[i]),
                centre_range_bin=float(stats.range_bin[i]), centre_angle_bin=float(stats.angle_bin[i]),
                doppler_bin=float(stats.doppler_bin[i]),
            )
            for i, c in enumerate(class_ids, start=1)
        )
        return RadarFrame(cube=cube, profile=CARRADA, sequence=sequence, index=index, labels=labels,
                          instances=instances, objects=objects, extras={"frame_name": name})

    def frames(self, sequence: str | None = None) -> Iterator[RadarFrame]:
        for seq in [sequence] if sequence is not None else self.sequences():
            for index in range(self.n_frames(seq)):
                yield self.read_frame(seq, index)
