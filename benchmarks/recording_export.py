"""Exporting a predictions store of 100 frames as recordings, on one core: MCAP with Foxglove's schemas, Rerun's
.rrd and the MCAP of ROS 2 messages (``radarseg export recording``'s writers), each timed over the whole store.

The store holds a simulated recording's ground truth as predictions (``small`` preset, 5 sequences x 20 frames,
tracked by segment-batch's own pass: tests/pipelines/recordings/truth_store.py), so its voxels and objects are those
of real scenes; the log power is read from the recording as the command reads it. The process is pinned to one core
(``os.sched_setaffinity``): every thread of the writers shares it; ``cpu_median_s`` is the process's CPU time
(every thread), the figure a loaded machine does not inflate. Goal: <= 10 s per format. Figures go to
benchmarks/results/recording_export.json with the CPU, its flags and the load average; nothing is asserted.

    .venv/bin/python -m benchmarks.recording_export [--sequences 5] [--frames 20] [--repeats 3]
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.harness import int_options_main

RESULTS = Path(__file__).resolve().parent / "results" / "recording_export.json"


def machine() -> dict[str, object]:
    """The machine as the harness describes it (CPU model, flags, cores), with the load average and the time."""
    from benchmarks.harness import machine as harness_machine

    return {**harness_machine(), "load_average": os.getloadavg(), "when": time.strftime("%Y-%m-%d %H:%M:%S")}


def run(sequences: int, frames: int, repeats: int) -> dict:
    from pipelines.recordings.export import WRITERS
    from pipelines.recordings.store_frames import open_store_recording, store_frames
    from tests.pipelines.recordings.truth_store import write_truth_predictions

    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core for every thread
    work = Path(tempfile.mkdtemp(prefix="radarseg-recording-bench-"))
    started = time.perf_counter()
    store = write_truth_predictions(work, sequences=sequences, frames=frames)
    build_s = time.perf_counter() - started
    recording = open_store_recording(store)
    before = machine()
    figures = {}
    for kind, writer in WRITERS.items():
        seconds, cpu_seconds = [], []
        for repeat in range(repeats):
            out = work / f"out-{kind}-{repeat}{'.rrd' if kind == 'rrd' else '.mcap'}"
            tick, cpu = time.perf_counter(), time.process_time()
            writer(store_frames(recording), recording.info, out)
            seconds.append(time.perf_counter() - tick)
            cpu_seconds.append(time.process_time() - cpu)
        figures[kind] = {"median_s": statistics.median(seconds), "min_s": min(seconds), "repeats": repeats,
                         "cpu_median_s": statistics.median(cpu_seconds),
                         "bytes": out.stat().st_size, "goal_s": 10.0}
    points = sum(len(frame.points) for frame in store_frames(recording, log_power=False))
    shutil.rmtree(work)
    return {"frames": len(recording), "labelled_points": points, "preset": recording.info.preset,
            "store_build_s": build_s, "export": figures, "machine_before": before, "machine_after": machine()}


def main(argv: list[str] | None = None) -> int:
    return int_options_main(RESULTS, run, __doc__, argv, sequences=5, frames=20, repeats=3)


if __name__ == "__main__":
    sys.exit(main())
