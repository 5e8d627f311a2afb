"""Ray job: RAD cubes into the zarr v3 store of inputs and targets (docs/design.md section 4).

::

    python -m pipelines.datasets.preprocess --sim --profile small --sequences 3 --frames 8 --seed 11 --out STORE.zarr
    python -m pipelines.datasets.preprocess --source recording:DIR --out STORE.zarr [--split-fractions 0.7 0.15 0.15]
    python -m pipelines.datasets.preprocess --source carrada:ROOT --out STORE.zarr      # split from data_seq_ref.json
    ray job submit --address http://127.0.0.1:8265 --working-dir . -- \
        python -m pipelines.datasets.preprocess ... --out /abs/STORE.zarr

The job follows :mod:`pipelines.jobs` (``add_arguments``, ``config_from_args``, ``main(cfg) -> dict``,
``format_result``; the options and the config in :mod:`pipelines.datasets.preprocess_options`) and runs on
:mod:`pipelines.datasets.sharded_job`. With no ``--address`` (and no ``RAY_ADDRESS``, which ``ray job submit`` sets
for its drivers) it starts an embedded local Ray with a capped object store; ``--in-process`` runs every shard in
the calling process without Ray (smoke runs).

How the work is cut: frames are laid out sequence by sequence (sequences sorted by name) in ``N``
store slots; every array is sharded along the frame axis every ``--shard-frames`` slots; one Ray task
per shard reads (or, for ``sim``, simulates: nothing but the store is written) its frames, encodes
them and writes the whole shard of every array, then its progress marker (last). At most ``--tasks``
shard tasks are in flight (``ray.wait``). A rerun with the same arguments skips shards whose marker
exists, so an interrupted job resumes and ends with the same arrays, byte for byte, as a straight run.

Bad cubes (unreadable, wrong shape or dtype, NaN/Inf) are not written: the slot keeps its fill
values with ``valid = 0`` and the frame goes to the quarantine list in the store's ``report``
attribute with the reason; the job carries on. A job whose every frame is bad fails.

Each shard task also returns the moments of the train frames' ``input`` per Doppler bin and the
class voxel counts; :func:`reduce_summaries` merges them (Chan's parallel variance, in shard order so
the result is deterministic) into the store's ``normalisation`` and ``class_voxel_counts`` attributes.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.datasets import shard_frames, sharded_job
from pipelines.datasets.preprocess_options import (  # noqa: F401 (the job's options: pipelines.jobs' contract)
    SOURCE_KINDS,
    PreprocessConfig,
    add_arguments,
    config_from_args,
)
from pipelines.datasets.sharded_store import check_resumable_out, mark_shard_done, write_shard_arrays
from pipelines.datasets.sources import SourceKind, parse_source
from pipelines.datasets.store import (
    FORMAT,
    OBJECT_FIELDS,
    SPLIT_CODE,
    SPLITS,
    StoreLayout,
    create_store,
    encode_frame,
)
from pipelines.jobs import run_module
from radar.errors import DataError, UserError
from radar.frame import RadarFrame
from radar.io.carrada import CarradaReader
from radar.io.recording import Recording
from radar.profiles import UnknownPresetError, get_profile
from radar.profiles.files import ProfileError, profile_to_dict
from radar.schema import cube_schema
from radar.simulate import SimulatorConfig, sequence_name, simulate_sequence

log = logging.getLogger(__name__)

DEFAULT_SPLIT_FRACTIONS = (0.7, 0.15, 0.15)


@dataclass(frozen=True)
class Slot(sharded_job.FrameSlot):
    """One frame slot of the store, with the split of its sequence."""

    split: int  # SPLIT_CODE

    def slot_arrays(self) -> dict[str, int]:
        return {**super().slot_arrays(), "split": self.split}


@dataclass(frozen=True)
class JobPlan(sharded_job.ShardedPlan):
    """Everything fixed before any work: the source, the store layout, the slot of every frame (``Slot``s)
    and the split rule."""

    split_rule: dict[str, Any]
    simulator: dict[str, Any] | None = None  # version and options of the simulator behind the frames (None: not one)

    def identity(self) -> dict[str, Any]:
        """What a resumed run must share with the run that created the store (a store begun by another
        simulator version is not continued by this one)."""
        return {"source": self.source.to_dict(), "layout": self.layout.to_dict(), "sequences": list(self.sequences),
                "split_rule": self.split_rule,
                "slots": [[s.sequence_id, s.index, s.split] for s in self.frames], "simulator": self.simulator}


# --------------------------------------------------------------------------- planning
def _split_by_fractions(sequences: Sequence[str], fractions: Sequence[float]) -> dict[str, str]:
    """Contiguous runs of sequences in name order: train, then val, then test. Counts are ``fraction * n`` rounded
    by largest remainder; then every split of non-zero fraction that got none takes one sequence from the largest
    split, in split order, while the largest holds two or more (3 sequences: one per split at 0.7/0.15/0.15)."""
    n = len(sequences)
    exact = np.asarray(fractions, np.float64) * n
    counts = np.floor(exact + 1e-9).astype(int)
    for i in np.argsort(-(exact - counts), kind="stable")[: n - int(counts.sum())]:
        counts[i] += 1
    for i, fraction in enumerate(fractions):
        donor = int(np.argmax(counts))
        if fraction > 0 and counts[i] == 0 and counts[donor] >= 2:
            counts[donor] -= 1
            counts[i] += 1
    names = [split for split, count in zip(SPLITS, counts, strict=True) for _ in range(count)]
    return dict(zip(sequences, names, strict=True))


def plan_job(cfg: PreprocessConfig) -> JobPlan:
    """Check every argument and the source's metadata, and lay out the store. Raises ValueError or
    DataError saying what is wrong; nothing is written."""
    source_of_frames = parse_source(cfg.source, SOURCE_KINDS)
    kind, location = source_of_frames.kind, source_of_frames.location or ""
    for name in ("tasks", "shard_frames", "max_objects"):
        value = getattr(cfg, name)
        if value is not None and value < 1:
            raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
    if cfg.split_fractions is not None:
        fractions = tuple(float(f) for f in cfg.split_fractions)
        if len(fractions) != 3 or min(fractions) < 0 or abs(sum(fractions) - 1) > 1e-6 or fractions[0] <= 0:
            raise UserError(f"--split-fractions must be 3 non-negative numbers (train > 0) summing to 1, "
                             f"got {list(cfg.split_fractions)}")
    if not cfg.out:
        raise UserError("--out must name the store path")

    splits: dict[str, str]
    if kind is SourceKind.SIM:
        preset = cfg.preset or "small"
        try:
            profile = get_profile(preset)
        except (UnknownPresetError, ProfileError) as exc:
            raise UserError(f"--preset: {exc}") from None
        n_sequences = 2 if cfg.sequences is None else cfg.sequences
        n_frames = 8 if cfg.frames is None else cfg.frames
        if n_sequences < 1 or n_frames < 1:
            raise UserError(f"--sequences and --frames must be >= 1, got {n_sequences} and {n_frames}")
        source = sharded_job.SourceSpec("sim", None, preset, cfg.seed)
        simulator = SimulatorConfig().stamp()  # the frames are simulated in the tasks with the default options
        frame_counts = {sequence_name(i): n_frames for i in range(n_sequences)}
    else:
        given = [f"--{n}" for n in ("preset", "sequences", "frames") if getattr(cfg, n) is not None]
        if given or cfg.seed != 0:
            raise UserError(f"{', '.join(given + (['--seed'] if cfg.seed else []))}: only with --source sim "
                             f"(the {kind} source fixes them)")
        root = Path(location).expanduser().absolute()
        reader = CarradaReader(root) if kind is SourceKind.CARRADA else Recording(root)
        if kind is SourceKind.ADC_RECORDING and reader.content != "adc":
            raise UserError(f"--source {cfg.source!r}: {root} holds RAD cubes, not ADC samples (use recording:DIR)")
        # the store records a seed for any source
        source = sharded_job.SourceSpec(kind, str(root), reader.profile.name, seed=0)
        profile = reader.profile  # a file-described radar is known by its recording, not by name
        frame_counts = {seq: reader.n_frames(seq) for seq in sorted(reader.sequences())}
        simulator = reader.meta.get("simulator") if isinstance(reader, Recording) else None
        if not any(frame_counts.values()):
            raise DataError(root, "the source holds no frame")
        if kind is SourceKind.CARRADA and cfg.split_fractions is None:
            splits = {seq: reader.split(seq) for seq in frame_counts}
    names = tuple(sorted(frame_counts))
    if kind is not SourceKind.CARRADA or cfg.split_fractions is not None:
        fractions = cfg.split_fractions or DEFAULT_SPLIT_FRACTIONS
        splits = _split_by_fractions(names, fractions)
        split_rule = {"rule": "fractions", "fractions": list(fractions)}
        empty = [split for split, f in zip(SPLITS, fractions, strict=True) if f > 0 and split not in splits.values()]
        if empty:
            wanted = sum(f > 0 for f in fractions)
            log.warning("--split-fractions %s over %d sequences: the %s split(s) get no sequence (one per split needs "
                        "at least %d sequences); train with --val-split none, or preprocess more --sequences",
                        " ".join(f"{f:g}" for f in fractions), len(names), ", ".join(map(repr, empty)), wanted)
    else:
        split_rule = {"rule": "carrada data_seq_ref.json"}
    if not any(splits[s] == "train" and frame_counts[s] for s in names):
        raise UserError(f"the split rule {split_rule} leaves the train split empty ({len(names)} sequences); "
                         "the normalisation statistics need train frames")

    slots: list[Slot] = []
    for sequence_id, seq in enumerate(names):
        for index in range(frame_counts[seq]):
            slots.append(Slot(len(slots), sequence_id, seq, index, SPLIT_CODE[splits[seq]]))
    layout = StoreLayout(profile, len(slots), cfg.shard_frames, max_objects=cfg.max_objects)
    plan = JobPlan(cfg=cfg, out=Path(cfg.out).expanduser().absolute(), source=source, layout=layout, sequences=names,
                   frames=tuple(slots), split_rule=split_rule, simulator=simulator)
    _check_out(plan)
    return plan


def _check_out(plan: JobPlan) -> None:
    """An existing ``--out`` must be empty, or a store made by the same job (which is then resumed)."""
    check_resumable_out(plan.out, store_format=FORMAT, identity=plan.identity(), what="radarseg store")


# --------------------------------------------------------------------------- frames of a source
def simulated_frames(preset: str, seed: int, sequence_index: int, indices: Sequence[int]) -> Iterator[RadarFrame]:
    """Frames ``indices`` (ascending) of simulated sequence ``sequence_index``, exactly as a full
    ``simulate_sequence`` run yields them, without synthesising the frames before the first one."""
    n_frames = max(indices) + 1 if indices else 0
    return simulate_sequence(preset, n_frames, seed=seed, sequence_index=sequence_index, only=indices)


def _source_frames(source: sharded_job.SourceSpec,
                   slots: Sequence[Slot]) -> Iterator[tuple[Slot, RadarFrame | DataError]]:
    """Each slot's frame, or the DataError that reading it raised."""
    if source.kind == "sim":
        by_sequence: dict[int, list[Slot]] = {}
        for slot in slots:
            by_sequence.setdefault(slot.sequence_id, []).append(slot)
        for sequence_id, group in by_sequence.items():
            frames = simulated_frames(source.preset, source.seed, sequence_id, [s.index for s in group])
            yield from zip(group, frames, strict=True)
        return
    reader = CarradaReader(source.path) if source.kind == "carrada" else Recording(source.path)
    for slot in slots:
        try:
            yield slot, reader.read_frame(slot.sequence, slot.index)
        except DataError as exc:
            yield slot, exc


# --------------------------------------------------------------------------- the shard task
def _frame_moments(values: np.ndarray) -> dict[str, Any]:
    """Count, mean and sum of squared deviations per Doppler bin of a (R, A, D) float16 cube."""
    x = values.astype(np.float64).reshape(-1, values.shape[-1])
    mean = x.mean(axis=0)
    return {"count": int(x.shape[0]), "mean": mean, "m2": ((x - mean) ** 2).sum(axis=0)}


def _merge_moments(a: dict[str, Any] | None, b: dict[str, Any] | None) -> dict[str, Any] | None:
    """Chan et al.'s parallel combination of two per-Doppler-bin moment sets (either may be None)."""
    if a is None or b is None:
        return a if b is None else b
    n = a["count"] + b["count"]
    mean_a, mean_b = np.asarray(a["mean"]), np.asarray(b["mean"])
    delta = mean_b - mean_a
    return {"count": n, "mean": mean_a + delta * (b["count"] / n),
            "m2": np.asarray(a["m2"]) + np.asarray(b["m2"]) + delta**2 * (a["count"] * b["count"] / n)}


def process_shard(job: sharded_job.ShardJob) -> dict[str, Any]:
    """Encode the frames of one shard, write the whole shard of every array, then its marker.

    Returns (and stores in the marker) the shard's summary: frames written, quarantined frames with
    reasons, class voxel counts per split, and the train frames' ``input`` moments per Doppler bin.
    """
    layout = job.layout
    buffers, quarantined = shard_frames.fill_shard(job, _source_frames(job.source, job.frames),
                                      lambda frame: encode_frame(frame, layout))
    start, _ = layout.shard_bounds(job.shard)
    num_classes = layout.profile.num_classes
    class_counts = {name: np.zeros(num_classes, np.int64) for name in SPLITS}
    moments = None
    for slot in job.frames:  # in slot order, so the moments merge in a fixed order
        k = slot.slot - start
        if not buffers["valid"][k]:
            continue
        class_counts[SPLITS[slot.split]] += np.bincount(buffers["labels"][k].ravel(), minlength=num_classes)
        if slot.split == SPLIT_CODE["train"]:
            moments = _merge_moments(moments, _frame_moments(buffers["input"][k]))
    write_shard_arrays(job.store, layout, job.shard, buffers)
    summary = {
        "shard": job.shard,
        "frames": len(job.frames),
        "written": int(buffers["valid"].sum()),
        "train_frames_written": int(sum(1 for s in job.frames
                                        if s.split == SPLIT_CODE["train"] and buffers["valid"][s.slot - start])),
        "quarantined": quarantined,
        "class_counts": {name: counts.tolist() for name, counts in class_counts.items()},
        "moments": None if moments is None else {"count": moments["count"], "mean": moments["mean"].tolist(),
                                                 "m2": moments["m2"].tolist()},
    }
    mark_shard_done(job.store, job.shard, summary)
    return summary


def reduce_summaries(summaries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Merge shard summaries (in shard order, so the float result does not depend on task timing)."""
    ordered = sorted(summaries, key=lambda s: s["shard"])
    moments = None
    class_counts: dict[str, np.ndarray] = {}
    for s in ordered:
        moments = _merge_moments(moments, s["moments"])
        for name, counts in s["class_counts"].items():
            class_counts[name] = class_counts.get(name, 0) + np.asarray(counts, np.int64)
    normalisation = None
    if moments is not None:
        mean_d, var_d = np.asarray(moments["mean"]), np.asarray(moments["m2"]) / moments["count"]
        mean = float(mean_d.mean())  # every Doppler bin has the same count
        var = float((var_d + (mean_d - mean) ** 2).mean())
        normalisation = {
            "mean": mean, "std": float(np.sqrt(var)),
            "mean_per_doppler": mean_d.tolist(), "std_per_doppler": np.sqrt(var_d).tolist(),
            "frames": int(sum(s["train_frames_written"] for s in ordered)),
            "voxels": int(moments["count"]) * len(mean_d), "units": "dB", "split": "train",
        }
    return {
        "frames": int(sum(s["frames"] for s in ordered)),
        "written": int(sum(s["written"] for s in ordered)),
        "quarantined": sorted((q for s in ordered for q in s["quarantined"]), key=lambda q: q["frame"]),
        "class_voxel_counts": {name: counts.tolist() for name, counts in class_counts.items()},
        "normalisation": normalisation,
    }


# --------------------------------------------------------------------------- the job
def store_attributes(plan: JobPlan, stats: dict[str, Any]) -> dict[str, Any]:
    """The store's final attributes from the plan and the reduced shard summaries (DataError when every
    frame, or every train frame, was quarantined)."""
    check_stats(plan, stats)
    profile = plan.layout.profile
    return {
        "preset": profile.name,
        "radar_file": profile_to_dict(profile) if profile.chirp is not None else None,
        "schema": cube_schema(profile, "log_power_db"),  # what `input` holds
        "radar": profile.to_dict(),
        "class_names": list(profile.all_class_names),
        "splits": list(SPLITS),
        "sequences": list(plan.sequences),
        "object_fields": list(OBJECT_FIELDS),
        "normalisation": stats["normalisation"],
        "class_voxel_counts": stats["class_voxel_counts"],
        "report": {"frames": stats["frames"], "written": stats["written"], "quarantined": stats["quarantined"]},
        "source": plan.source.to_dict(),
        "split_rule": plan.split_rule,
        "simulator": plan.simulator,  # {"version", "options"} of the simulator that made the frames, or None
        "job": plan.cfg.to_dict(),
    }


def check_stats(plan: JobPlan, stats: dict[str, Any]) -> None:
    """Fail (DataError) when every frame, or every train frame, was quarantined."""
    where = plan.source.path or f"sim:{plan.source.preset}"
    if stats["written"] == 0:
        reasons = "; ".join(f"{q['sequence']}/{q['index']}: {q['reason']}" for q in stats["quarantined"][:3])
        raise DataError(where, f"every one of the {stats['frames']} input frames is bad, nothing to "
                               f"preprocess (first: {reasons})")
    if stats["normalisation"] is None:
        raise DataError(where, "every train frame is bad: no normalisation statistics can be computed")


def main(cfg: PreprocessConfig) -> dict[str, Any]:
    """Run the job; returns its figures (frames, written, quarantined, shards run/skipped, seconds)."""
    plan = plan_job(cfg)  # every argument is checked before Ray starts or anything is written
    job = sharded_job.ShardedJob(plan=plan, create_store=create_store, stage=process_shard, reduce=reduce_summaries,
                                 finish=partial(store_attributes, plan))
    execution = sharded_job.Execution(in_process=cfg.in_process, address=cfg.address, workers=cfg.tasks,
                                      progress=cfg.progress, desc=f"preprocess {plan.source.preset}")
    run = sharded_job.run_sharded(job, execution)
    return {
        "store": str(plan.out),
        "frames": run.stats["frames"],
        "written": run.stats["written"],
        "quarantined": len(run.stats["quarantined"]),
        "shards": plan.layout.n_shards,
        "shards_run": run.shards_run,
        "shards_skipped": run.shards_skipped,
        "tasks_in_flight": run.workers,
        "seconds_ray_start": run.seconds_start,
        "seconds_shards": run.seconds_shards,
        "seconds_total": run.seconds_total,
        "frames_per_second": run.frames_per_second,
    }


def format_result(result: dict[str, Any]) -> str:
    """The summary line (``--json`` prints the figures as one JSON line instead: what drivers of ``ray job
    submit`` read)."""
    return (f"store {result['store']}: {result['written']}/{result['frames']} frames written, "
            f"{result['quarantined']} quarantined, {result['shards_run']} shards run, "
            f"{result['shards_skipped']} already done")


if __name__ == "__main__":
    sys.exit(run_module("pipelines.datasets.preprocess"))
