"""Region-growing settings for a new radar, from a short sweep on its own simulated frames.

Region growing's right settings depend on the radar: the disc radius on how far an object's energy spreads in
x-y (its angle resolution at range), the SNR floor on its noise and dynamic range, bridging on whether its array
splits an object into separate blobs. For each combination of a grid of disc radii, floors and bridge sizes
(intensity ratio 0: on every built-in radar the floor binds, and the paper's ratio of 0.5 cut recall to 0.6-0.8)
this grows regions from the true centres of simulated frames and measures recall (object voxels inside the ROI,
over all frames) and the mean ROI size. The chosen settings are the most compact ROI that reaches the target
recall; where nothing does, the highest recall. The grid of disc radii is stated for a 50 m road radar and shrinks
with a radar that sees less (:func:`search_distances`: 0.5-2.5 m for a radar of 6.25 m, as many range bins as 4-20 m
are on the 50 m ones). ``radarseg radar tune-growing PROFILE`` prints the table to add
to the profile file (``[region_growing]``), and ``--write`` puts it there (:func:`write_settings`).
"""

from __future__ import annotations

import itertools
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radar.profiles import RadarProfile, get_profile
from radar.profiles.files import load_profile_file
from radar.profiles.scene_settings import radar_scale
from radar.region_growing import RegionGrowingConfig, grow_regions, noise_level_db
from radar.simulate import simulate_sequence
from radar.transforms import log_power

DISTANCES_M = (4.0, 6.0, 8.0, 12.0, 16.0, 20.0)
FLOORS_DB = (4.0, 5.0, 6.0)
BRIDGES = (0, 1, 2)
TARGET_RECALL = 0.95


def search_distances(profile: RadarProfile) -> tuple[float, ...]:
    """The disc radii searched for ``profile``: :data:`DISTANCES_M` (set for the 50 m radars) times
    :func:`radar.profiles.scene_settings.radar_scale`; unchanged for every built-in preset."""
    scale = radar_scale(profile)
    return tuple(round(d * scale, 4) for d in DISTANCES_M)


@dataclass(frozen=True)
class SweepRow:
    """One combination: its settings, recall from the true centres and the mean ROI voxels per frame."""

    distance_m: float
    min_snr_db: float
    bridge: int
    recall: float
    roi_voxels: float


@dataclass(frozen=True)
class SweepResult:
    profile: str
    frames: int
    target_recall: float
    rows: tuple[SweepRow, ...]
    chosen: SweepRow
    reached: bool  # whether the chosen row reaches the target recall

    def settings(self) -> dict[str, float | int]:
        """The ``[region_growing]`` table of the chosen row."""
        return {"distance_m": self.chosen.distance_m, "min_snr_db": self.chosen.min_snr_db,
                "intensity_ratio": 0.0, "bridge": self.chosen.bridge}

    def toml(self) -> str:
        values = "\n".join(f"{key} = {value}" for key, value in self.settings().items())
        return f"[region_growing]\n{values}\n"


def _frames(profile: RadarProfile, sequences: int, frames: int, seed: int) -> list[tuple]:
    """(log power, noise level, true-centre seeds, instances) of each simulated frame that holds an object."""
    out = []
    for index in range(sequences):
        for frame in simulate_sequence(profile, frames, seed=seed, sequence_index=index):
            seeds = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects
                              if o.n_voxels], float).reshape(-1, 3)
            if len(seeds):
                cube = log_power(frame.cube)
                out.append((cube, noise_level_db(cube), seeds, frame.instances))
    return out


def sweep_growing(profile: str | RadarProfile, *, sequences: int = 6, frames: int = 2, seed: int = 0,
                  target_recall: float = TARGET_RECALL, distances_m: Sequence[float] | None = None,
                  floors_db: Sequence[float] = FLOORS_DB, bridges: Sequence[int] = BRIDGES,
                  progress: Callable[[int, int], None] | None = None) -> SweepResult:
    """Sweep the grid on ``sequences x frames`` simulated frames of ``profile`` (see the module docstring); the
    disc radii default to the radar's :func:`search_distances`."""
    if sequences < 1 or frames < 1:
        raise ValueError(f"sequences and frames must be >= 1, got {sequences} and {frames}")
    if not 0.0 < target_recall <= 1.0:
        raise ValueError(f"target recall must be in (0, 1], got {target_recall}")
    profile = get_profile(profile)
    distances_m = search_distances(profile) if distances_m is None else distances_m
    data = _frames(profile, sequences, frames, seed)
    if not data:
        raise ValueError(f"no simulated frame of {profile.name!r} holds a labelled object; simulate more frames")
    total = sum(int(np.count_nonzero(instances)) for *_, instances in data)
    grid = list(itertools.product(distances_m, floors_db, bridges))
    rows = []
    for done, (distance, floor, bridge) in enumerate(grid, 1):
        config = RegionGrowingConfig(intensity_ratio=0.0, distance_m=distance, min_snr_db=floor, bridge=bridge)
        found = voxels = 0
        for cube, noise_db, seeds, instances in data:
            regions = grow_regions(cube, seeds, profile, config, noise_db=noise_db)
            found += int(np.count_nonzero(instances[tuple(regions.voxels.T)]))
            voxels += len(regions)
        rows.append(SweepRow(distance, floor, bridge, found / max(total, 1), voxels / len(data)))
        if progress is not None:
            progress(done, len(grid))
    reaching = [row for row in rows if row.recall >= target_recall]
    chosen = min(reaching, key=lambda r: r.roi_voxels) if reaching else max(rows, key=lambda r: r.recall)
    return SweepResult(profile.name, len(data), target_recall, tuple(rows), chosen, bool(reaching))


def write_settings(path: str | Path, result: SweepResult) -> Path:
    """Put the chosen settings into the profile file at ``path`` (a ``.toml``'s ``[region_growing]`` table replaced
    or appended, its other lines kept; a ``.json``'s ``region_growing`` key), then check that the file loads with
    them. Written atomically."""
    path = Path(path)
    text = path.read_text()
    if path.suffix == ".json":
        data = json.loads(text)
        data["region_growing"] = result.settings()
        new = json.dumps(data, indent=2) + "\n"
    elif path.suffix == ".toml":
        kept, skipping = [], False
        for line in text.splitlines():
            header = line.strip()
            if header.startswith("["):
                skipping = header == "[region_growing]"
            if not skipping:
                kept.append(line)
        new = "\n".join(kept).rstrip() + "\n\n" + result.toml()
    else:
        raise ValueError(f"{path}: a profile file is .toml or .json")
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    tmp.write_text(new)
    written = load_profile_file(tmp)
    if dict(written.region_growing) != result.settings():
        tmp.unlink()
        raise ValueError(f"{path}: the rewritten file does not read back the settings")
    os.replace(tmp, path)
    return path
