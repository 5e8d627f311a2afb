"""What a predictions store (batch segmentation's output, :mod:`pipelines.inference.predictions_store`) holds, in
figures
and pictures: ``radarseg store info PRED.zarr`` and the report ``segment-batch`` writes beside the store.

Figures: frames segmented and quarantined, predicted voxels per class, detections per frame (mean, range,
histogram) and per class, MACs and seconds per frame. Pictures: the RA and RD views of the frames with the most
detections, the predicted masks and objects drawn over them (the views read back from the job's source). Tracks
(the ``tracks`` array, when the store has one): how many, their length, the tracked objects' speed; the pictures
name each object's track.
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from pipelines.inference.predictions_store import COMPUTE_FIELDS, PREDICTION_OBJECT_FIELDS, open_predictions
from radar.profiles import resolve_profile

OBJ = {name: i for i, name in enumerate(PREDICTION_OBJECT_FIELDS)}
CMP = {name: i for i, name in enumerate(COMPUTE_FIELDS)}
READ_FRAMES = 16  # labels read this many frames at a time (R x A x D bytes each)


def summarise_predictions(path: str | Path) -> dict[str, Any]:
    """The figures of a finished predictions store (DataError when it is not one)."""
    group = open_predictions(path)
    attrs = group.attrs.asdict()
    names = list(attrs["class_names"])
    valid = group["valid"][:].astype(bool)
    n_objects = group["n_objects"][:].astype(int)[valid]
    voxels = np.zeros(len(names), np.int64)
    for start in range(0, len(valid), READ_FRAMES):
        labels = group["labels"][start:start + READ_FRAMES][valid[start:start + READ_FRAMES]]
        voxels += np.bincount(labels.ravel(), minlength=len(names))[:len(names)]
    objects = group["objects"][:][valid]
    classes = objects[..., OBJ["class_id"]]
    per_class = {name: int((classes == c).sum()) for c, name in enumerate(names) if c}
    compute = group["compute"][:][valid]
    report = attrs.get("report", {})
    tracks = _tracks_summary(group, valid, n_objects) if "tracks" in group else None
    return {
        "kind": "predictions",
        "path": str(path),
        "preset": attrs["preset"],
        "source": attrs.get("source"),
        "split": attrs.get("split"),
        "frames": int(len(valid)),
        "segmented": int(valid.sum()),
        "quarantined": report.get("quarantined", []),
        "class_voxels": {name: int(v) for name, v in zip(names, voxels, strict=True)},
        "detections_per_frame": {
            "mean": float(n_objects.mean()) if len(n_objects) else 0.0,
            "min": int(n_objects.min()) if len(n_objects) else 0, "max": int(n_objects.max(initial=0)),
            "frames_without": int((n_objects == 0).sum()),
            "histogram": {str(k): int(v) for k, v in enumerate(np.bincount(n_objects)) if v},
        },
        "detections_per_class": per_class,
        "macs_per_frame": float(compute[:, CMP["macs_total"]].mean()) if len(compute) else 0.0,
        "seconds_per_frame": float(compute[:, CMP["seconds_total"]].mean()) if len(compute) else 0.0,
        "roi_voxels_per_frame": float(compute[:, CMP["roi_voxels"]].mean()) if len(compute) else 0.0,
        "tracks": tracks,
    }


def _tracks_summary(group: Any, valid: np.ndarray, n_objects: np.ndarray) -> dict[str, Any]:
    """Tracks (distinct ids per sequence), their length in frames and the speed of the tracked objects."""
    tracks = group["tracks"][:][valid]
    sequence_id = group["sequence_id"][:][valid]
    ids = tracks[..., 0]
    rows = np.isfinite(ids)
    pairs = np.column_stack([np.broadcast_to(sequence_id[:, None], ids.shape)[rows], ids[rows]])
    lengths = np.unique(pairs, axis=0, return_counts=True)[1] if len(pairs) else np.zeros(0, int)
    speed = np.hypot(tracks[..., 1], tracks[..., 2])[rows]
    figures = group.attrs.get("tracking", {})
    return {"tracks": int(len(lengths)), "confirmed": figures.get("confirmed_tracks"),
            "objects_tracked": int(rows.sum()), "objects": int(n_objects.sum()),
            "frames_per_track": {"mean": float(lengths.mean()) if len(lengths) else 0.0,
                                 "max": int(lengths.max(initial=0))},
            "speed_mps": {"median": float(np.median(speed)) if len(speed) else 0.0,
                          "max": float(speed.max(initial=0.0))},
            "ms_per_frame": figures.get("ms_per_frame")}


def format_predictions(summary: dict[str, Any]) -> str:
    """``store info``'s text for a predictions store."""
    source = summary["source"] or {}
    det = summary["detections_per_frame"]
    lines = [f"predictions store {summary['path']} (preset {summary['preset']}; source {source.get('kind')}:"
             f"{source.get('path')}{', split ' + summary['split'] if summary['split'] else ''})",
             f"frames: {summary['frames']} ({summary['segmented']} segmented, {len(summary['quarantined'])} "
             f"quarantined)",
             f"detections per frame: mean {det['mean']:.2f}, min {det['min']}, max {det['max']}, "
             f"{det['frames_without']} frames without; histogram {det['histogram']}",
             "detections per class: " + ", ".join(f"{k} {v}" for k, v in summary["detections_per_class"].items()),
             "predicted voxels per class: " + ", ".join(f"{k} {v}" for k, v in summary["class_voxels"].items()),
             f"per frame: {summary['macs_per_frame'] / 1e9:.3f} GMACs, {summary['seconds_per_frame'] * 1e3:.0f} ms, "
             f"{summary['roi_voxels_per_frame']:.0f} ROI voxels", _format_tracks(summary.get("tracks"))]
    for q in summary["quarantined"][:5]:
        lines.append(f"  quarantined: {q}")
    return "\n".join(lines)


def _format_tracks(tracks: dict[str, Any] | None) -> str:
    if tracks is None:
        return "tracks: none (a store written before segment-batch tracked objects)"
    return (f"tracks: {tracks['tracks']} ({tracks['confirmed']} confirmed), {tracks['objects_tracked']}/"
            f"{tracks['objects']} objects with a track id; {tracks['frames_per_track']['mean']:.1f} frames a track "
            f"(max {tracks['frames_per_track']['max']}); speed median {tracks['speed_mps']['median']:.2f} m/s, "
            f"max {tracks['speed_mps']['max']:.2f} m/s")


def _log_power(source: dict[str, Any], slot: int, sequence: str, index: int) -> np.ndarray:
    """(R, A, D) log power of one segmented frame, read back from the job's source."""
    if source["kind"] == "store":
        from pipelines.datasets.store import open_store

        return open_store(source["path"])["input"][slot].astype(np.float32)
    from radar.io.recording import Recording

    return Recording(source["path"]).read_frame(sequence, index).log_power()


def report_dir(path: str | Path) -> Path:
    """Where ``segment-batch`` writes its report: ``data/pred.zarr`` -> ``data/pred-report/``."""
    path = Path(path)
    return path.with_name(f"{path.name.removesuffix('.zarr')}-report")


def write_predictions_report(path: str | Path, out: str | Path | None = None, *, pictures: int = 3) -> dict[str, Any]:
    """``summary.json``, ``summary.txt`` and ``pictures`` frame pictures (most detections first) in ``out``
    (default :func:`report_dir`); returns ``{"dir", "summary", "pictures"}``."""
    from pipelines.figures import plot_prediction

    out = Path(out) if out is not None else report_dir(path)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarise_predictions(path)
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    (out / "summary.txt").write_text(format_predictions(summary) + "\n")
    group = open_predictions(path)
    profile = resolve_profile(summary["preset"], group.attrs.get("radar_file"), source=str(path))
    names = list(group.attrs["class_names"])
    sequences = list(group.attrs["sequences"])
    valid = group["valid"][:].astype(bool)
    n_objects = group["n_objects"][:]
    order = [int(i) for i in np.argsort(-n_objects, kind="stable") if valid[i]][:pictures]
    drawn = []
    for i in sorted(order):
        table = group["objects"][i][: int(n_objects[i])]
        ids = group["tracks"][i][: len(table), 0] if "tracks" in group else np.full(len(table), np.nan)
        objects = [SimpleNamespace(class_name=names[int(row[OBJ["class_id"]])]
                                   + (f" #{int(track)}" if np.isfinite(track) else ""), score=float(row[OBJ["score"]]),
                                   x=float(row[OBJ["x"]]), y=float(row[OBJ["y"]]),
                                   velocity_mps=float(row[OBJ["velocity_mps"]]))
                   for row, track in zip(table, ids, strict=True)]
        sequence, index = sequences[int(group["sequence_id"][i])], int(group["frame_index"][i])
        source_slot = int(group["source_slot"][i])
        log_power = _log_power(summary["source"], source_slot, sequence, index)
        # named by the source's slot, as radarseg evaluate names the frames of a store
        drawn.append(plot_prediction(log_power, profile, group["ra_mask"][i], group["rd_mask"][i], objects,
                                     out / f"frame_{source_slot:05d}.png",
                                     title=f"{sequence} frame {index}: {len(objects)} objects labelled; masks: "
                                           f"predicted classes").name)
    return {"dir": str(out), "summary": summary, "pictures": drawn}
