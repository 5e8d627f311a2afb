"""Scenes as sequences: objects on smooth trajectories at the profile's frame rate, entering and
leaving the field of view, and the static clutter they move through (docs/design.md section 3.1)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from radar.profiles import RadarProfile
from radar.simulate.targets import class_model


@dataclass(frozen=True)
class ObjectState:
    """One object at one frame. Position (m), heading (rad from +x), speed (m/s), RCS (dBsm)."""

    track_id: int
    class_id: int  # 1-based: index into profile.class_names + 1
    class_name: str
    x: float
    y: float
    heading: float
    speed: float
    yaw_rate: float  # rad/s
    rcs_dbsm: float  # mean total RCS of the object (fluctuates per frame around it)
    gait_phase: float

    @property
    def range_m(self) -> float:
        return float(np.hypot(self.x, self.y))

    @property
    def angle_deg(self) -> float:
        return float(np.degrees(np.arctan2(self.x, self.y)))

    @property
    def vx(self) -> float:
        """Velocity across the line of sight at boresight (m/s, x lateral)."""
        return float(self.speed * np.cos(self.heading))

    @property
    def vy(self) -> float:
        """Velocity forward (m/s)."""
        return float(self.speed * np.sin(self.heading))

    @property
    def radial_velocity(self) -> float:
        """Radial velocity of the object's centre (m/s, positive receding)."""
        return float((self.x * self.vx + self.y * self.vy) / max(self.range_m, 1e-6))


@dataclass(frozen=True)
class StaticClutter:
    """Zero-Doppler scatterers: ground returns, a guard rail, buildings/poles, and TX-RX coupling."""

    x: np.ndarray
    y: np.ndarray
    rcs_dbsm: np.ndarray
    # Flat reflecting surfaces that make multipath ghosts of the moving objects (radar/simulate/multipath.py), one
    # row each: unit normal (nx, ny), distance d of the plane n . p = d from the radar (m), and the loss of one
    # bounce off it (dB, <= 0). Road scenes have none.
    mirrors: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))


def in_field_of_view(profile: RadarProfile, x: float, y: float, margin: float = 0.0) -> bool:
    rng = np.hypot(x, y)
    angle = np.degrees(np.arctan2(x, y))
    return bool(1.5 < rng < profile.max_range * 0.95 - margin and abs(angle) < profile.max_angle_deg - margin)


def _random_point_in_fov(profile: RadarProfile, rng: np.random.Generator, *, edge: bool) -> tuple[float, float]:
    max_r = profile.max_range * 0.9
    if edge and rng.random() < 0.5:  # far edge
        r = rng.uniform(0.75, 0.9) * max_r
        ang = rng.uniform(-0.8, 0.8) * profile.max_angle_deg
    elif edge:  # lateral edge
        r = rng.uniform(0.15, 0.8) * max_r
        ang = rng.choice([-1, 1]) * rng.uniform(0.8, 0.92) * profile.max_angle_deg
    else:
        r = max_r * np.sqrt(rng.uniform(0.02, 0.7))  # uniform in area, denser towards the middle
        ang = rng.uniform(-0.85, 0.85) * profile.max_angle_deg
    t = np.radians(ang)
    return float(r * np.sin(t)), float(r * np.cos(t))


class SceneGenerator:
    """Generates the object states of one sequence, frame after frame, reproducibly from ``rng``.

    The number of objects in view stays within ``profile.objects_per_frame``: objects that leave
    the field of view are dropped, and new ones enter at its edges (or appear inside it at the start).
    """

    def __init__(self, profile: RadarProfile, rng: np.random.Generator, *, min_separation_m: float = 3.0):
        self.profile = profile
        self.rng = rng
        self.min_separation_m = min_separation_m
        self.objects: list[ObjectState] = []
        self.next_track_id = 1
        self.frame_index = 0
        lo, hi = profile.objects_per_frame
        for _ in range(int(rng.integers(lo, hi + 1))):
            self._spawn(edge=False)

    def _spawn(self, *, edge: bool) -> None:
        profile, rng = self.profile, self.rng
        for _ in range(50):  # rejection sampling for a free spot
            x, y = _random_point_in_fov(profile, rng, edge=edge)
            if all(np.hypot(x - o.x, y - o.y) >= self.min_separation_m for o in self.objects):
                break
        else:
            return
        class_id = int(rng.integers(1, len(profile.class_names) + 1))
        class_name = profile.class_names[class_id - 1]
        model = class_model(class_name)
        # Head towards a random point in view, so the object stays a while; speeds within the
        # class's range and, on short-range radars, within the unambiguous velocity.
        tx, ty = _random_point_in_fov(profile, rng, edge=False)
        heading = float(np.arctan2(ty - y, tx - x)) if edge else float(rng.uniform(-np.pi, np.pi))
        speed = float(rng.uniform(*model.speed))
        speed = min(speed, 0.9 * profile.max_velocity)
        state = ObjectState(
            track_id=self.next_track_id, class_id=class_id, class_name=class_name, x=x, y=y,
            heading=heading, speed=speed, yaw_rate=float(rng.normal(0.0, 0.08)),
            rcs_dbsm=float(rng.uniform(*model.rcs_dbsm)), gait_phase=float(rng.uniform(0, 2 * np.pi)),
        )
        self.next_track_id += 1
        self.objects.append(state)

    def step(self) -> list[ObjectState]:
        """The objects of the current frame, then advances the scene by one frame period."""
        current = list(self.objects)
        dt = self.profile.frame_period_s
        moved = []
        for o in self.objects:
            heading = o.heading + o.yaw_rate * dt
            yaw_rate = float(np.clip(o.yaw_rate + self.rng.normal(0.0, 0.03), -0.4, 0.4))
            x = o.x + o.speed * np.cos(heading) * dt
            y = o.y + o.speed * np.sin(heading) * dt
            if in_field_of_view(self.profile, x, y):
                moved.append(replace(o, x=float(x), y=float(y), heading=float(heading), yaw_rate=yaw_rate))
        self.objects = moved
        lo, hi = self.profile.objects_per_frame
        while len(self.objects) < lo:
            before = len(self.objects)
            self._spawn(edge=True)
            if len(self.objects) == before:
                break
        if len(self.objects) < hi and self.rng.random() < 0.05:
            self._spawn(edge=True)
        self.frame_index += 1
        return current


def static_clutter(profile: RadarProfile, rng: np.random.Generator) -> StaticClutter:
    """Static scatterers of one scene (all at zero Doppler; the radar is static, as in CARRADA)."""
    max_r = profile.max_range
    xs, ys, rcs = [], [], []
    # Ground and low clutter: many weak returns spread over the field of view.
    n_ground = int(rng.integers(60, 100))
    r = max_r * np.sqrt(rng.uniform(0.002, 0.95, n_ground))
    a = np.radians(rng.uniform(-80, 80, n_ground))
    xs.append(r * np.sin(a))
    ys.append(r * np.cos(a))
    rcs.append(rng.uniform(-22, -10, n_ground))
    # A guard rail or kerb along one side, in half of the scenes.
    if rng.random() < 0.5:
        side = rng.choice([-1, 1]) * rng.uniform(0.15, 0.3) * max_r
        y_rail = np.arange(max(2.0, abs(side) * 0.5), max_r * 0.95, max_r / 50)
        xs.append(np.full(len(y_rail), side))
        ys.append(y_rail)
        rcs.append(rng.uniform(-12, -4, len(y_rail)))
    # Buildings, poles and parked structures: a few strong points far away.
    n_strong = int(rng.integers(5, 15))
    r = rng.uniform(0.5, 0.97, n_strong) * max_r
    a = np.radians(rng.uniform(-75, 75, n_strong))
    xs.append(r * np.sin(a))
    ys.append(r * np.cos(a))
    rcs.append(rng.uniform(5, 20, n_strong))
    # TX-RX coupling seen as a very near, very strong static return.
    xs.append(np.array([0.0]))
    ys.append(np.array([0.3 * profile.range_resolution / 0.1953125]))
    rcs.append(np.array([-45.0]))
    return StaticClutter(np.concatenate(xs), np.concatenate(ys), np.concatenate(rcs))
