"""The tracks picture of the tracking guide's comparison (docs/guides/tracking.md): each tracker's reported tracks over
one sequence, drawn on its last frame's RA view (max log power over Doppler, in Cartesian metres), from the objects
``evaluate --trackers`` tracked (its ``tracking_frames.npz``) and the store they came from.
Each track is a polyline of its reported positions with its id and a velocity arrow (its last estimate, 1 s long);
the simulator's true tracks are dashed white with their true velocity.

    .venv/bin/python -m experiments.studies.tracker_comparison_figure --store STORE --frames OUT/tracking_frames.npz \
        [--sequence N] [--trackers radarseg,stonesoup-gnn,...] [--out docs/images/tracker_comparison_tracks.png]

Without ``--sequence`` it draws the sequence with the most true tracks.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from experiments.studies.tracking_figure import draw_tracks, sequence_frames

REPO = Path(__file__).resolve().parents[2]


def main() -> None:
    import matplotlib.pyplot as plt

    from pipelines.evaluation.tracker_comparison import TRACKERS, load_frames, parse_trackers, run_reported
    from pipelines.evaluation.tracking import by_sequence
    from pipelines.figures import save_figure
    from radar.tracking import TrackerConfig

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--frames", required=True, help="tracking_frames.npz of evaluate --trackers on that store")
    parser.add_argument("--sequence", type=int)
    parser.add_argument("--trackers", type=parse_trackers, default=tuple(TRACKERS))
    parser.add_argument("--out", default=str(REPO / "docs" / "images" / "tracker_comparison_tracks.png"))
    args = parser.parse_args()
    profile, sequence, name, store_frames = sequence_frames(args.store, args.sequence)
    group = by_sequence(f for f in load_frames(args.frames) if f.sequence_id == sequence)[sequence]
    truth = defaultdict(list)
    for frame in group:
        t = frame.truth
        for k, track_id in enumerate(t.track_id.tolist()):
            truth[track_id].append((t.x[k], t.y[k], t.vx[k], t.vy[k]))
    columns = min(2, len(args.trackers))
    rows = -(-len(args.trackers) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(7 * columns, 4.8 * rows), squeeze=False)
    config = TrackerConfig.for_profile(profile)
    for ax, tracker in zip(axes.ravel(), args.trackers, strict=False):
        answers = run_reported({sequence: group}, tracker, config).answers[sequence]
        paths, velocity = defaultdict(list), {}
        for hyp in answers:
            for k, track_id in enumerate(hyp.track_id.tolist()):
                paths[track_id].append(tuple(hyp.xy[k]))
                velocity[track_id] = np.asarray(hyp.velocity[k])
        draw_tracks(ax, profile, store_frames[-1][1], paths, velocity, truth, f"{tracker} ({len(paths)} tracks)")
    for ax in axes.ravel()[len(args.trackers):]:
        ax.set_visible(False)
    fig.suptitle(f"{Path(args.store).name} sequence {sequence} ({name}), frames {group[0].frame_index}-"
                 f"{group[-1].frame_index}: reported tracks (solid, id, velocity arrow = 1 s) on the same objects\n"
                 f"and true tracks (dashed white), on the last frame's RA view")
    fig.tight_layout()
    print(save_figure(fig, args.out))


if __name__ == "__main__":
    main()
