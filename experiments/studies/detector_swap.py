"""End-to-end time per frame with a new detector against the one it replaces, the same segmenter, side by side.

Both pairs segment the frames of one simulated sequence (after a warm-up frame each), interleaved per frame and
in alternating order, ``--rounds`` times; a detector that reads earlier frames gets the sequence's previous frame
as a stream would give it, and is also timed alone on single cubes. One thread. Prints the median frame of each
and the ratio to the old detector; writes benchmarks/results/detector_swap.json with the CPU flags and the load
average. Never asserts a time.

    .venv/bin/python -m experiments.studies.detector_swap --old OLD.pt --new checkpoints/detector.pt \
        [--segmenter checkpoints/segmenter.pt] [--frames 13] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import torch

from benchmarks.sparse_conv import machine_info
from models.erasenet.model import EraseNet
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "experiments" / "reports" / "detector_swap.json"


def time_pairs(old: EraseNet, new: EraseNet, frames: list, rounds: int) -> dict[str, list[float]]:
    """Seconds per frame of each way of running, interleaved per frame."""
    ways = {"old": lambda i: old.segment(frames[i], kind=InputKind.log_power),
            "new, single cube": lambda i: new.segment(frames[i], kind=InputKind.log_power)}
    if new.history_frames:
        ways["new, earlier frames as history"] = lambda i: new.segment(
            frames[i], kind=InputKind.log_power, history=frames[max(0, i - new.history_frames):i][::-1])
    times: dict[str, list[float]] = {name: [] for name in ways}
    for name in ways:  # warm-up: traced graphs (the history one at its first use), first kernel maps
        ways[name](1)
    for index in range(rounds):
        for i in range(1, len(frames)):
            order = list(ways) if (i + index) % 2 == 0 else list(reversed(ways))
            for name in order:
                started = time.perf_counter()
                ways[name](i)
                times[name].append(time.perf_counter() - started)
    return times


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", required=True, help="the detector checkpoint being replaced")
    parser.add_argument("--new", default=str(REPO / "checkpoints" / "detector.pt"))
    parser.add_argument("--segmenter", default=str(REPO / "checkpoints" / "segmenter.pt"))
    parser.add_argument("--frames", type=int, default=13, help="frames of the simulated sequence (seed 77)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    old = EraseNet.from_checkpoints(args.old, args.segmenter)
    new = EraseNet.from_checkpoints(args.new, args.segmenter)
    frames = [scene.log_power() for scene in simulate_sequence(old.profile.name, args.frames, seed=77)]
    before = os.getloadavg()
    with torch.no_grad():
        times = time_pairs(old, new, frames, args.rounds)
    medians = {name: 1e3 * statistics.median(values) for name, values in times.items()}
    results = {"old": args.old, "new": args.new, "segmenter": args.segmenter, "frames": args.frames,
               "rounds": args.rounds, "threads": 1, "history_frames": new.history_frames, "median_ms": medians,
               "over_old": {name: value / medians["old"] for name, value in medians.items()},
               "load_average_before": before, "load_average_after": os.getloadavg(), "machine": machine_info(),
               "when": time.strftime("%Y-%m-%d %H:%M:%S")}
    for name, value in medians.items():
        print(f"{name:32s} {value:7.1f} ms per frame  {results['over_old'][name]:.2f}x the old detector's")
    print(f"load average {before[0]:.2f} -> {results['load_average_after'][0]:.2f}")
    Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()
