"""Multi-object tracking of a radar's objects over a sequence (docs/design.md section 16).

An extended Kalman filter per track in Cartesian coordinates, state ``[x, y, vx, vy]`` (m, m/s; x lateral,
positive to the right, y forward), with a constant-velocity motion model driven by white acceleration noise.
A measurement is one object of a frame: its position ``(x, y)`` and the radial velocity the radar measures
(m/s, positive receding), ``h(s) = [x, y, (x vx + y vy) / r]``. The radial velocity is what makes a track's
velocity vector observable from its first frames; the lateral component comes from the positions over time.
Its innovation is wrapped into the radar's unambiguous interval (a Doppler that aliased stays near its track).

Each frame: every track is predicted to the frame's time, objects are assigned to tracks by the Mahalanobis
distance of their innovation (gated by a chi-square bound and a distance in metres) with
:func:`scipy.optimize.linear_sum_assignment`, assigned tracks are updated, and every object left over starts a
new track. A track is ``tentative`` until it has ``confirm_hits`` hits, then ``confirmed``; a confirmed track
that misses a frame is ``lost`` (coasted on its prediction) for up to ``max_misses`` frames before it is
dropped; a tentative track that misses a frame is dropped. Frames not seen at all (``step(frames=k)``, a gap)
count as misses of a confirmed track, not of a tentative one (unless the gap is longer than ``max_misses``).
Its class is the vote of its objects' classes, weighted by their detector scores.

The whole tracker state is a small JSON-able dict (:meth:`Tracker.to_state`, :meth:`Tracker.from_state`): a few
hundred bytes per track, so a service can keep a stream's tracks in a database between frames.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from enum import StrEnum
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from radar.profiles import RadarProfile

STATE_VERSION = 1
TYPICAL_SPEED_SIGMA_MPS = {"pedestrian": 1.5, "person": 1.5, "cyclist": 4.0, "motorcycle": 8.0, "car": 8.0,
                           "truck": 8.0}
"""A prior on the speed of a road user of each class (m/s): a new track's velocity across the line of sight."""
_NOT_ALLOWED = 1e9  # assignment cost of a pair outside the gate


class TrackStatus(StrEnum):
    tentative = "tentative"  # fewer than confirm_hits hits
    confirmed = "confirmed"  # updated in its last frame
    lost = "lost"  # confirmed, but missed its last frame(s): coasted on its prediction


@dataclass(frozen=True)
class TrackerConfig:
    """Parameters of the tracker (units in the names). :meth:`for_profile` derives them from a radar profile."""

    frame_period_s: float
    max_radial_velocity_mps: float  # the radar's unambiguous |radial velocity|: innovations wrap at +-this
    range_sigma_m: float = 0.35  # measurement noise of an object's position along the line of sight
    azimuth_sigma_rad: float = 0.02  # and across it (as an angle)
    min_position_sigma_m: float = 1.0  # floor on either, for an object's centre moving within its extent
    radial_velocity_sigma_mps: float = 0.4
    acceleration_sigma_mps2: float = 4.0  # white acceleration noise of the constant-velocity model
    initial_speed_sigma_mps: float = 6.0  # a new track's unknown velocity across the line of sight
    # the same per class id (1-based; index 0 unused), for classes with a typical speed (TYPICAL_SPEED_SIGMA_MPS)
    class_speed_sigma_mps: tuple[float, ...] = ()
    gate_chi2: float = 16.27  # Mahalanobis bound of an assignment (chi-square, 3 dof, 0.999)
    gate_m: float = 4.0  # and a bound in metres between a track's predicted position and an object
    confirm_hits: int = 2
    max_misses: int = 3  # frames a confirmed track is coasted before it is dropped
    tentative_max_misses: int = 1  # frames seen without its object that a tentative track survives

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "class_speed_sigma_mps":
                if not all(np.isfinite(v) and v > 0 for v in value):
                    raise ValueError(f"class_speed_sigma_mps must hold finite numbers > 0, got {value!r}")
            elif f.name in ("confirm_hits", "max_misses", "tentative_max_misses"):
                if not isinstance(value, int) or value < (1 if f.name == "confirm_hits" else 0):
                    raise ValueError(f"{f.name} must be an integer >= {1 if f.name == 'confirm_hits' else 0}, "
                                     f"got {value!r}")
            elif not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
                raise ValueError(f"{f.name} must be a finite number > 0, got {value!r}")

    @classmethod
    def for_profile(cls, profile: RadarProfile, **overrides: Any) -> TrackerConfig:
        """The radar's frame period, unambiguous velocity and resolutions, then the settings its profile file states
        (``[tracking]``, ``RadarProfile.tracking``); ``overrides`` replace any field."""
        values: dict[str, Any] = {
            "frame_period_s": profile.frame_period_s,
            "max_radial_velocity_mps": profile.max_velocity,
            "range_sigma_m": max(profile.range_resolution, 0.2),
            "azimuth_sigma_rad": 2.0 / profile.n_angle,  # one angle bin at boresight (bins uniform in sin)
            # an object's Doppler (its voxels' mean) wanders over bins and its labelled centre need not move
            # as it does (part of it out of view): a loose radial velocity keeps identities
            "radial_velocity_sigma_mps": max(2.5 * profile.velocity_resolution, 0.1),
            "class_speed_sigma_mps": (1.0, *(TYPICAL_SPEED_SIGMA_MPS.get(name, cls.initial_speed_sigma_mps)
                                             for name in profile.class_names)),
        }
        return cls(**{**values, **dict(profile.tracking), **overrides})

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Measurements:
    """The objects of one frame, N rows: position (m), radial velocity (m/s, positive receding), class id
    (1-based) and detector score (the weight of its class vote)."""

    x: np.ndarray
    y: np.ndarray
    radial_velocity: np.ndarray
    class_id: np.ndarray
    score: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.x)
        if not all(len(v) == n for v in (self.y, self.radial_velocity, self.class_id, self.score)):
            raise ValueError("Measurements fields must all have the same length")
        for name in ("x", "y", "radial_velocity", "score"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"Measurements.{name} must be finite")

    def __len__(self) -> int:
        return len(self.x)

    @classmethod
    def from_objects(cls, objects: list[Any]) -> Measurements:
        """From objects with ``x``, ``y``, ``velocity_mps``, ``class_id`` and ``score`` attributes (ERASE-Net's
        :class:`models.erasenet.model.SegmentedObject`)."""
        def column(name: str, dtype: Any = np.float64) -> np.ndarray:
            return np.array([getattr(o, name) for o in objects], dtype=dtype).reshape(-1)

        return cls(column("x"), column("y"), column("velocity_mps"), column("class_id", np.int64), column("score"))

    @classmethod
    def empty(cls) -> Measurements:
        return cls(*(np.zeros(0) for _ in range(3)), np.zeros(0, np.int64), np.zeros(0))


@dataclass
class Track:
    """One track: its filter state and its history in frames."""

    id: int
    mean: np.ndarray  # (4,) x, y, vx, vy
    cov: np.ndarray  # (4, 4)
    votes: dict[int, float]  # class id -> summed detector score of its objects
    status: TrackStatus = TrackStatus.tentative
    age: int = 1  # frames since it started, its first included
    hits: int = 1  # frames with an object assigned
    misses: int = 0  # consecutive frames without one, up to the last

    @property
    def class_id(self) -> int:
        return max(self.votes.items(), key=lambda kv: (kv[1], -kv[0]))[0]

    def summary(self) -> dict[str, Any]:
        """What a client sees of the track: position (m), velocity vector (m/s), speed (m/s), heading (degrees
        from +x, counter-clockwise, as the simulator's), class, age, hits, misses and status."""
        x, y, vx, vy = (float(v) for v in self.mean)
        return {"track_id": self.id, "class_id": self.class_id, "status": str(self.status), "x": x, "y": y,
                "vx": vx, "vy": vy, "speed": float(np.hypot(vx, vy)),
                "heading_deg": float(np.degrees(np.arctan2(vy, vx))),
                "age": self.age, "hits": self.hits, "misses": self.misses}

    def to_state(self) -> dict[str, Any]:
        upper = self.cov[np.triu_indices(4)]
        return {"id": self.id, "mean": [float(v) for v in self.mean], "cov": [float(v) for v in upper],
                "votes": {str(k): float(v) for k, v in self.votes.items()}, "status": str(self.status),
                "age": self.age, "hits": self.hits, "misses": self.misses}

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> Track:
        cov = np.zeros((4, 4))
        cov[np.triu_indices(4)] = state["cov"]
        cov = cov + np.triu(cov, 1).T
        return cls(id=int(state["id"]), mean=np.asarray(state["mean"], np.float64), cov=cov,
                   votes={int(k): float(v) for k, v in state["votes"].items()}, status=TrackStatus(state["status"]),
                   age=int(state["age"]), hits=int(state["hits"]), misses=int(state["misses"]))


@dataclass(frozen=True)
class TrackerStep:
    """What one frame did: the track id of each of its objects (in the measurements' order) and every track
    alive after it."""

    track_ids: np.ndarray  # (N,) int64
    tracks: list[Track]

    @property
    def object_tracks(self) -> list[Track]:
        """The track of each object, in the measurements' order."""
        by_id = {t.id: t for t in self.tracks}
        return [by_id[int(i)] for i in self.track_ids]

    @property
    def confirmed(self) -> list[Track]:
        """Tracks confirmed and updated in this frame, and those coasted (lost)."""
        return [t for t in self.tracks if t.status is not TrackStatus.tentative]


@dataclass
class Tracker:
    """Tracks over one sequence: call :meth:`step` once per frame, in order."""

    config: TrackerConfig
    tracks: list[Track] = field(default_factory=list)
    next_id: int = 1
    frames: int = 0  # frames stepped so far

    # ----------------------------------------------------------------- the filter
    def _transition(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        F = np.eye(4)
        F[0, 2] = F[1, 3] = dt
        q = self.config.acceleration_sigma_mps2 ** 2
        block = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        Q = np.zeros((4, 4))
        Q[np.ix_([0, 2], [0, 2])] = block
        Q[np.ix_([1, 3], [1, 3])] = block
        return F, Q

    def _position_cov(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """(n, 2, 2) measurement covariances of positions: range and azimuth noise rotated to x-y."""
        cfg = self.config
        r = np.maximum(np.hypot(x, y), 1e-3)
        radial = np.stack([x / r, y / r], axis=-1)
        across = np.stack([radial[:, 1], -radial[:, 0]], axis=-1)
        sigma_r = max(cfg.range_sigma_m, cfg.min_position_sigma_m)
        sigma_a = np.maximum(cfg.azimuth_sigma_rad * r, cfg.min_position_sigma_m)
        return (sigma_r**2 * radial[:, :, None] * radial[:, None, :]
                + (sigma_a**2)[:, None, None] * across[:, :, None] * across[:, None, :])

    def _innovation(self, mean: np.ndarray, cov: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
        """Innovations y (n, 3), their covariances S (n, 3, 3) and Jacobians H (n, 3, 4) of n objects z (n, 3)
        against n track states (mean (n, 4), cov (n, 4, 4))."""
        x, y, vx, vy = mean.T
        r = np.maximum(np.hypot(x, y), 1e-3)
        radial_velocity = (x * vx + y * vy) / r
        H = np.zeros((len(z), 3, 4))
        H[:, 0, 0] = H[:, 1, 1] = 1.0
        H[:, 2] = np.stack([vx / r - radial_velocity * x / r**2, vy / r - radial_velocity * y / r**2, x / r, y / r],
                           axis=-1)
        R = np.zeros((len(z), 3, 3))
        R[:, :2, :2] = self._position_cov(z[:, 0], z[:, 1])
        R[:, 2, 2] = self.config.radial_velocity_sigma_mps ** 2
        span = 2 * self.config.max_radial_velocity_mps
        innovation = np.stack([z[:, 0] - x, z[:, 1] - y, (z[:, 2] - radial_velocity + span / 2) % span - span / 2],
                              axis=-1)
        return innovation, H @ cov @ H.transpose(0, 2, 1) + R, H

    def _new_track(self, z: np.ndarray, class_id: int, score: float) -> Track:
        """A track at the object's position, moving at its radial velocity along the line of sight, with the
        velocity across it unknown (``initial_speed_sigma_mps``)."""
        cfg = self.config
        r = max(float(np.hypot(z[0], z[1])), 1e-3)
        radial = np.array([z[0], z[1]]) / r
        across = np.array([radial[1], -radial[0]])
        cov = np.zeros((4, 4))
        cov[:2, :2] = self._position_cov(z[None, 0], z[None, 1])[0]
        cov[2:, 2:] = (cfg.radial_velocity_sigma_mps**2 * np.outer(radial, radial)
                       + self._speed_sigma(class_id) ** 2 * np.outer(across, across))
        mean = np.array([z[0], z[1], *(z[2] * radial)])
        track = Track(id=self.next_id, mean=mean, cov=cov, votes={class_id: score})
        if cfg.confirm_hits <= 1:
            track.status = TrackStatus.confirmed
        self.next_id += 1
        return track

    def _speed_sigma(self, class_id: int) -> float:
        sigmas = self.config.class_speed_sigma_mps
        return sigmas[class_id] if 0 < class_id < len(sigmas) else self.config.initial_speed_sigma_mps

    # ----------------------------------------------------------------- one frame
    def step(self, measurements: Measurements, *, frames: int = 1) -> TrackerStep:
        """Advance by ``frames`` frame periods (more than 1: the frames between were not seen; their tracks are
        coasted) and take this frame's objects."""
        if not isinstance(frames, int) or frames < 1:
            raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
        cfg = self.config
        F, Q = self._transition(frames * cfg.frame_period_s)
        if self.tracks:
            means = np.array([t.mean for t in self.tracks]) @ F.T
            covs = F @ np.array([t.cov for t in self.tracks]) @ F.T + Q
        for k, track in enumerate(self.tracks):
            track.mean, track.cov = means[k], covs[k]
            track.age += frames
            # frames not seen: a confirmed track coasts through them (they count towards max_misses); a
            # tentative one is judged on the frames seen, but no gap longer than max_misses keeps it
            if track.status is not TrackStatus.tentative or frames - 1 > cfg.max_misses:
                track.misses += frames - 1
        self.tracks = [t for t in self.tracks if self._alive(t)]

        z = np.column_stack([measurements.x, measurements.y, measurements.radial_velocity]).reshape(-1, 3)
        rows, cols, gains = self._assign(z)
        track_ids = np.zeros(len(z), np.int64)
        assigned = set()
        if len(rows):  # the Kalman update of every assigned track at once
            innovation, S, H = (np.array([gains[i, j][n] for i, j in zip(rows, cols, strict=True)]) for n in range(3))
            P = np.array([self.tracks[i].cov for i in rows])
            K = P @ H.transpose(0, 2, 1) @ np.linalg.inv(S)
            means = np.array([self.tracks[i].mean for i in rows]) + (K @ innovation[..., None])[..., 0]
            covs = (np.eye(4) - K @ H) @ P
            covs = (covs + covs.transpose(0, 2, 1)) / 2
        for k, (i, j) in enumerate(zip(rows, cols, strict=True)):
            track = self.tracks[i]
            track.mean, track.cov = means[k], covs[k]
            class_id = int(measurements.class_id[j])
            track.votes[class_id] = track.votes.get(class_id, 0.0) + float(measurements.score[j])
            track.hits += 1
            track.misses = 0
            if track.status is TrackStatus.lost or track.hits >= cfg.confirm_hits:
                track.status = TrackStatus.confirmed
            track_ids[j] = track.id
            assigned.add(i)
        for i, track in enumerate(self.tracks):
            if i not in assigned:
                track.misses += 1
                if track.status is TrackStatus.confirmed:
                    track.status = TrackStatus.lost
        self.tracks = [t for t in self.tracks if self._alive(t)]
        for j in sorted(set(range(len(z))) - set(cols.tolist())):
            track = self._new_track(z[j], int(measurements.class_id[j]), float(measurements.score[j]))
            self.tracks.append(track)
            track_ids[j] = track.id
        self.frames += frames
        return TrackerStep(track_ids, list(self.tracks))

    def predicted_positions(self, *, frames: int = 1) -> np.ndarray:
        """(T, 2) where each confirmed or lost track expects its object ``frames`` frame periods on (x, y in m),
        without changing any track: the prior of the next frame's detection (:mod:`radar.track_priors`).
        Tentative tracks predict nothing."""
        if not isinstance(frames, int) or frames < 1:
            raise ValueError(f"frames must be an integer >= 1, got {frames!r}")
        F, _ = self._transition(frames * self.config.frame_period_s)
        means = [t.mean for t in self.tracks if t.status is not TrackStatus.tentative]
        return (np.array(means) @ F.T)[:, :2] if means else np.zeros((0, 2))

    def _alive(self, track: Track) -> bool:
        if track.status is TrackStatus.tentative:
            return track.misses <= self.config.tentative_max_misses
        return track.misses <= self.config.max_misses

    def _assign(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """Tracks (rows) and objects (columns) assigned to each other, and the innovation of every gated pair."""
        n_tracks, n_objects = len(self.tracks), len(z)
        cost = np.full((n_tracks, n_objects), _NOT_ALLOWED)
        gains: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        if n_tracks and n_objects:
            means, covs = np.array([t.mean for t in self.tracks]), np.array([t.cov for t in self.tracks])
            near = np.hypot(z[None, :, 0] - means[:, None, 0], z[None, :, 1] - means[:, None, 1]) <= self.config.gate_m
            rows, cols = np.nonzero(near)
            innovation, S, H = self._innovation(means[rows], covs[rows], z[cols])
            distance = np.einsum("ni,ni->n", innovation, np.linalg.solve(S, innovation[..., None])[..., 0])
            # + log det S: among equally close pairs, the better-known track wins (the NN cost of a GNN)
            log_det = np.log(np.linalg.det(S))
            for k in np.flatnonzero(distance <= self.config.gate_chi2):
                i, j = int(rows[k]), int(cols[k])
                cost[i, j] = distance[k] + log_det[k]
                gains[i, j] = (innovation[k], S[k], H[k])
        if not gains:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), gains
        shift = -min(cost[pair] for pair in gains)  # costs >= 0, so a gated pair always beats no pair
        rows, cols = linear_sum_assignment(np.where(cost < _NOT_ALLOWED, cost + shift, _NOT_ALLOWED))
        keep = cost[rows, cols] < _NOT_ALLOWED
        return rows[keep], cols[keep], gains

    # ----------------------------------------------------------------- state
    def to_state(self) -> dict[str, Any]:
        """Everything needed to continue the sequence, JSON-able."""
        return {"version": STATE_VERSION, "next_id": self.next_id, "frames": self.frames,
                "tracks": [t.to_state() for t in self.tracks]}

    @classmethod
    def from_state(cls, config: TrackerConfig, state: dict[str, Any]) -> Tracker:
        """The tracker :meth:`to_state` described (ValueError for a state of another version)."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"tracker state version {state.get('version')!r}, expected {STATE_VERSION}")
        return cls(config, [Track.from_state(t) for t in state["tracks"]], int(state["next_id"]),
                   int(state["frames"]))
