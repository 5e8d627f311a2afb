"""The picture of experiments/reports/tracking.md: tracks over one sequence drawn on its last frame's RA view
(max log power over Doppler, in Cartesian metres). Left: the tracker over the shipped pair's objects; right: over the
true centres.
Each track is a polyline of its objects' positions with its id and a velocity arrow (its last estimate, 1 s long);
the simulator's true tracks (labelled centres) are dashed white with their true velocity in a thin arrow.

    .venv/bin/python -m experiments.studies.tracking_figure --store /tmp/trk.zarr [--sequence N] \
        [--out experiments/reports/tracking_tracks.png]

Without ``--sequence`` it draws the sequence with the most true tracks.
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from radar.input_kind import InputKind

REPO = Path(__file__).resolve().parents[2]


def sequence_frames(store: str, sequence: int | None):
    from pipelines.datasets.store import OBJECT_COLUMN, open_store, store_profile
    from pipelines.evaluation.tracking import TruthObjects

    root = open_store(store)
    profile = store_profile(root.attrs.asdict(), store)
    valid, sequence_id, frame_index = root["valid"][:].astype(bool), root["sequence_id"][:], root["frame_index"][:]
    if sequence is None:  # the sequence with the most true tracks
        counts = defaultdict(set)
        for slot in np.flatnonzero(valid):
            table = root["objects"][slot][: int(root["n_objects"][slot])]
            counts[int(sequence_id[slot])].update(table[:, OBJECT_COLUMN["track_id"]].astype(int).tolist())
        sequence = max(sorted(counts), key=lambda s: len(counts[s]))
    slots = np.flatnonzero(valid & (sequence_id == sequence))
    slots = slots[np.argsort(frame_index[slots])]
    frames = [(int(frame_index[s]), root["input"][s].astype(np.float32),
               TruthObjects.from_table(root["objects"][s][: int(root["n_objects"][s])], profile)) for s in slots]
    return profile, sequence, root.attrs["sequences"][sequence], frames


def _paths(measurements, config):
    """Track id -> [(x, y)] and its last velocity, from running the tracker over ``measurements``."""
    from radar.tracking import Tracker

    tracker, paths, velocity = Tracker(config), defaultdict(list), {}
    for m in measurements:
        step = tracker.step(m)
        for j, track in enumerate(step.object_tracks):
            paths[track.id].append((m.x[j], m.y[j]))
            velocity[track.id] = track.mean[2:].copy()
    return paths, velocity


def draw_tracks(ax, profile, log_power, paths, velocity, truth, title):
    from radar import transforms

    x, y = profile.ra_cartesian
    ra = transforms.ra_view(log_power, kind=InputKind.log_power)
    ax.pcolormesh(x, y, ra, cmap="viridis", shading="nearest", rasterized=True)
    for points in truth.values():
        p = np.array([q[:2] for q in points])
        ax.plot(p[:, 0], p[:, 1], "--", color="white", lw=1.0, zorder=5)
        vx, vy = points[-1][2:]
        ax.arrow(p[-1, 0], p[-1, 1], vx, vy, color="white", width=0.04, head_width=0.45, length_includes_head=True,
                 zorder=5)
    colours = ["#ff4040", "#ffd000", "#40c0ff", "#ff80ff", "#ff9900", "#ffffff", "#60ff60"]
    for n, (track_id, points) in enumerate(sorted(paths.items())):
        p = np.array(points)
        colour = colours[n % len(colours)]
        ax.plot(p[:, 0], p[:, 1], "-o", color=colour, lw=1.5, ms=2.5)
        vx, vy = velocity[track_id]
        ax.arrow(p[-1, 0], p[-1, 1], vx, vy, color=colour, width=0.12, head_width=0.9, length_includes_head=True)
        ax.annotate(f"#{track_id}", p[-1], color=colour, fontsize=8, xytext=(4, 4), textcoords="offset points")
    ax.set(xlim=(-profile.max_range * 0.9, profile.max_range * 0.9), ylim=(0, profile.max_range), aspect="equal",
           xlabel="x (m, right > 0)", ylabel="y (m, forward)", title=title)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--store", required=True)
    parser.add_argument("--sequence", type=int)
    parser.add_argument("--out", default=str(REPO / "experiments" / "reports" / "tracking_tracks.png"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    import matplotlib.pyplot as plt

    from models.erasenet.model import EraseNet
    from pipelines.figures import save_figure
    from radar.tracking import Measurements, TrackerConfig

    profile, sequence, name, frames = sequence_frames(args.store, args.sequence)
    net = EraseNet.from_checkpoints(REPO / "checkpoints" / "detector.pt", REPO / "checkpoints" / "segmenter.pt")
    config = TrackerConfig.for_profile(profile)
    predicted = [Measurements.from_objects(net.segment(lp, kind=InputKind.log_power).objects) for _, lp, _ in frames]
    truth_in = [t.measurements() for _, _, t in frames]
    truth = defaultdict(list)
    for _, _, t in frames:
        for k, track_id in enumerate(t.track_id.tolist()):
            truth[track_id].append((t.x[k], t.y[k], t.vx[k], t.vy[k]))
    fig, axes = plt.subplots(1, 2, figsize=(14, 4.8))
    for ax, measurements, what in ((axes[0], predicted, "the shipped pair's objects"),
                                   (axes[1], truth_in, "the true centres")):
        paths, velocity = _paths(measurements, config)
        draw_tracks(ax, profile, frames[-1][1], paths, velocity, truth, f"tracks from {what} ({len(paths)} tracks)")
    fig.suptitle(f"{Path(args.store).name} sequence {sequence} ({name}), frames {frames[0][0]}-{frames[-1][0]}: "
                 f"tracks (solid, id, velocity arrow = 1 s) and true tracks (dashed white) on the last frame's RA view")
    fig.tight_layout()
    print(save_figure(fig, args.out))


if __name__ == "__main__":
    main()
