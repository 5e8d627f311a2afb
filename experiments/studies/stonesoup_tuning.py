"""Tuning Stone Soup's trackers (pipelines/evaluation/stonesoup_trackers.py) on the objects of a tuning seed, as ours
was tuned (experiments/reports/tracking.md): a small grid over each tracker's own settings (clutter, detection
probability, the PHD's birth and extraction) and their motion noise, scored by mean GOSPA on the
frames ``evaluate --trackers`` saved (``tracking_frames.npz``); prints every point and the best per tracker, and
writes them to ``--out`` as JSON.

    .venv/bin/python -m experiments.studies.stonesoup_tuning --frames OUT/tracking_frames.npz [--preset small] \
        [--trackers stonesoup-jpda] [--grid '{"clutter_per_frame": [5, 10], "acceleration_sigma_mps2": [8, 16]}'] \
        [--out /tmp/stonesoup_tuning.json]

The best points become :class:`StoneSoupSettings`' defaults; the comparison itself runs on another seed.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

from pipelines.evaluation.tracker_comparison import compare_trackers, load_frames
from pipelines.evaluation.tracking import by_sequence, match_distances
from radar.profiles import get_profile
from radar.tracking import TrackerConfig

GRIDS = {  # tracker -> setting -> values
    "stonesoup-gnn": {},
    "stonesoup-jpda": {"clutter_per_frame": (0.5, 2.0, 5.0), "prob_detect": (0.7, 0.9)},
    "stonesoup-gmphd": {"clutter_per_frame": (0.5, 2.0), "birth_weight": (0.1, 0.5)},
}
ACCELERATION_MPS2 = (2.0, 4.0, 8.0)  # their motion noise (ours: TrackerConfig.acceleration_sigma_mps2, 4)


def points(grid: dict[str, tuple]) -> list[dict]:
    return [dict(zip(grid, values, strict=True)) for values in itertools.product(*grid.values())]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", required=True, help="tracking_frames.npz of evaluate --trackers on the tuning seed")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--trackers", default=",".join(GRIDS), help="comma-separated, of " + ", ".join(GRIDS))
    parser.add_argument("--grid", type=json.loads, help="instead of GRIDS and ACCELERATION_MPS2: one grid (JSON, "
                        "setting -> values, acceleration_sigma_mps2 among them) for every tracker named")
    parser.add_argument("--out", default="/tmp/stonesoup_tuning.json")
    args = parser.parse_args()
    profile = get_profile(args.preset)
    sequences = by_sequence(load_frames(args.frames))
    match_m = match_distances(profile)[0]
    config = TrackerConfig.for_profile(profile)
    rows = []
    for name in args.trackers.split(","):
        grid = args.grid or {**GRIDS[name], "acceleration_sigma_mps2": ACCELERATION_MPS2}
        for settings in points(grid):
            scores = compare_trackers(sequences, (name,), config, profile.class_names, match_m, {name: settings})[name]
            row = {"tracker": name, **settings,
                   "gospa_m": scores["gospa"]["mean_m"], "hota": scores["hota"]["hota"],
                   "mota": scores["mot"]["mota"], "idf1": scores["mot"]["idf1"]}
            rows.append(row)
            print(json.dumps(row), flush=True)
    best = {name: min((r for r in rows if r["tracker"] == name), key=lambda r: r["gospa_m"])
            for name in {r["tracker"] for r in rows}}
    for name, row in sorted(best.items()):
        print(f"best {name}: {row}")
    Path(args.out).write_text(json.dumps({"rows": rows, "best": best}, indent=2) + "\n")


if __name__ == "__main__":
    main()
