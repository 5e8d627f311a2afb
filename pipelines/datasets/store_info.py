"""What a job reads from a preprocessed store's attributes: the radar, the class names and the input
normalisation (the train split's statistics), checked against each other."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipelines.datasets.store import open_store, store_profile
from radar.errors import UserError
from radar.profiles import RadarProfile


@dataclass(frozen=True)
class StoreInfo:
    """A store's radar, classes and normalisation."""

    path: str
    profile: RadarProfile
    class_names: tuple[str, ...]  # background first
    normalisation: dict[str, Any]  # mean, std (dB), mean_per_doppler, std_per_doppler (D values)

    @classmethod
    def read(cls, path: str | Path) -> StoreInfo:
        attrs = open_store(path).attrs.asdict()
        stats = attrs["normalisation"]
        normalisation = {"mean": float(stats["mean"]), "std": float(stats["std"]),
                         "mean_per_doppler": [float(v) for v in stats["mean_per_doppler"]],
                         "std_per_doppler": [float(v) for v in stats["std_per_doppler"]]}
        profile = store_profile(attrs, path)
        names = tuple(attrs.get("class_names") or profile.all_class_names)
        if len(names) != profile.num_classes:
            raise UserError(f"store {path}: {len(names)} class names, preset {profile.name} has "
                             f"{profile.num_classes} classes")
        return cls(str(path), profile, names, normalisation)
