"""The frame type every reader and the simulator yield, and its object table."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from radar import transforms
from radar.profiles import RadarProfile


@dataclass(frozen=True)
class ObjectRecord:
    """One object of one frame.

    The ``true_*`` fields give the object's reference point and velocity as the scene placed and moved it
    (simulator) or as annotated (readers; NaN where a data set has none); the ``centre_*`` and
    ``doppler_bin`` fields are computed from the object's labelled voxels (mean Cartesian position,
    circular-mean Doppler bin), NaN when it has none.
    """

    instance_id: int  # value in the instance cube (1..N within the frame)
    class_id: int  # 1-based class label
    class_name: str
    n_voxels: int
    centre_x: float  # m
    centre_y: float  # m
    centre_range_bin: float
    centre_angle_bin: float
    doppler_bin: float
    true_range_m: float = float("nan")
    true_angle_deg: float = float("nan")
    true_velocity_mps: float = float("nan")  # radial, positive receding
    rcs_dbsm: float = float("nan")
    track_id: int = -1  # the object's identity across the frames of its sequence (-1: unknown)
    true_vx: float = float("nan")  # velocity vector (m/s; x lateral, y forward) as the scene moved it
    true_vy: float = float("nan")

    def to_dict(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and np.isnan(v) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ObjectRecord:
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"unknown object fields {sorted(unknown)}; expected a subset of {sorted(names)}")
        return cls(**{k: (float("nan") if v is None else v) for k, v in data.items()})


@dataclass
class RadarFrame:
    """One radar frame in the project's RAD convention (docs/design.md section 2).

    ``cube``: (R, A, D) complex64, or float32 magnitude for sources that store no phase.
    ``labels``: (R, A, D) uint8 class cube (0 = background); ``instances``: (R, A, D) uint8
    instance cube whose ids index ``objects``. Labels are None for unlabelled data.
    """

    cube: np.ndarray
    profile: RadarProfile
    sequence: str
    index: int
    labels: np.ndarray | None = None
    instances: np.ndarray | None = None
    objects: tuple[ObjectRecord, ...] = ()
    extras: dict[str, Any] = field(default_factory=dict, repr=False)

    def log_power(self) -> np.ndarray:
        """Model input ``10*log10(|I|^2 + 1)`` (R, A, D) float32 in dB."""
        return transforms.log_power(self.cube)

    def ra_mask(self) -> np.ndarray:
        """(R, A) uint8 projection of the class cube (docs/design.md section 8)."""
        return transforms.project_ra(self._require_labels(), self.profile.num_classes)

    def rd_mask(self) -> np.ndarray:
        """(R, D) uint8 projection of the class cube."""
        return transforms.project_rd(self._require_labels(), self.profile.num_classes)

    def _require_labels(self) -> np.ndarray:
        if self.labels is None:
            raise ValueError(f"frame {self.sequence}/{self.index} carries no labels")
        return self.labels
