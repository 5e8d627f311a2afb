"""Indoor scenes at the radar's own scale, from a profile's ``[scene]`` table (radar/profiles/scene_settings.py).

People walk about a room within the table's distances: they turn as they go and, instead of leaving the field of
view as road users do (radar/simulate/scene.py), turn back at its edges, so each frame holds the counts the table
states. The room's static reflectors sit at zero Doppler: walls (a back wall facing the radar, or a side wall
along the line of sight) as lines of point scatterers spaced at half the range resolution whose RCS falls off
away from normal incidence, furniture as small clusters of strong points, weak diffuse returns from floor and
ceiling, and the TX-RX coupling at the first range bins. The walls also reflect the walkers' echoes: multipath
ghosts, unlabelled (radar/simulate/multipath.py).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from radar.profiles import RadarProfile
from radar.profiles.scene_settings import SceneSettings
from radar.simulate.scene import ObjectState, StaticClutter
from radar.simulate.targets import class_model

TURN_SIGMA_RAD_S = 0.6  # how quickly a walker's heading wanders (rad/s, random walk of the yaw rate)
WALL_PEAK_RCS_DBSM = (-14.0, -2.0)  # a wall at normal incidence, per scatterer
FURNITURE_RCS_DBSM = (-28.0, -8.0)
DIFFUSE_RCS_DBSM = (-35.0, -20.0)
COUPLING_RCS_DBSM = (-65.0, -30.0)  # TX-RX coupling at 0.1 m, per room: 60 to 95 dB over the noise (a recorded TI
                                   # frame, tests/fixtures/openradar/, shows 63 dB)
WALL_BOUNCE_LOSS_DB = (-20.0, -8.0)  # one bounce off a wall, for the multipath ghosts (radar/simulate/multipath.py)


def _room_point(settings: SceneSettings, max_angle_deg: float, rng: np.random.Generator) -> tuple[float, float]:
    """A random point of the room's floor between the table's distances, uniform in area."""
    lo, hi = settings.range_m
    r = float(np.sqrt(rng.uniform(lo**2, hi**2)))
    angle = np.radians(rng.uniform(-0.85, 0.85) * max_angle_deg)
    return r * float(np.sin(angle)), r * float(np.cos(angle))


def _in_room(settings: SceneSettings, max_angle_deg: float, x: float, y: float) -> bool:
    lo, hi = settings.range_m
    return bool(lo <= np.hypot(x, y) <= hi and abs(np.degrees(np.arctan2(x, y))) <= 0.9 * max_angle_deg)


class IndoorSceneGenerator:
    """Object states of one indoor sequence, frame after frame, reproducibly from ``rng`` (the interface of
    :class:`radar.simulate.scene.SceneGenerator`: :meth:`step` gives the current frame's objects)."""

    def __init__(self, profile: RadarProfile, settings: SceneSettings, rng: np.random.Generator):
        self.profile, self.settings, self.rng = profile, settings, rng
        self.objects: list[ObjectState] = []
        self.next_track_id = 1
        for class_id, name in enumerate(profile.class_names, 1):
            lo, hi = settings.count_range(name)
            for _ in range(int(rng.integers(lo, hi + 1))):
                self._spawn(class_id, name)

    def _spawn(self, class_id: int, class_name: str) -> None:
        profile, settings, rng = self.profile, self.settings, self.rng
        for _ in range(50):  # rejection sampling for a free spot
            x, y = _room_point(settings, profile.max_angle_deg, rng)
            if all(np.hypot(x - o.x, y - o.y) >= settings.min_separation_m for o in self.objects):
                break
        else:
            return
        model = class_model(class_name)
        speed = float(rng.uniform(*(settings.speed_range(class_name) or model.speed)))
        self.objects.append(ObjectState(
            track_id=self.next_track_id, class_id=class_id, class_name=class_name, x=x, y=y,
            heading=float(rng.uniform(-np.pi, np.pi)), speed=min(speed, 0.9 * profile.max_velocity),
            yaw_rate=float(rng.normal(0.0, TURN_SIGMA_RAD_S)), rcs_dbsm=float(rng.uniform(*model.rcs_dbsm)),
            gait_phase=float(rng.uniform(0, 2 * np.pi))))
        self.next_track_id += 1

    def _walk(self, o: ObjectState, dt: float) -> ObjectState:
        """One frame period of walking; at the room's edge the walker turns towards a point inside it."""
        rng, max_angle = self.rng, self.profile.max_angle_deg
        heading = o.heading + o.yaw_rate * dt
        yaw_rate = float(np.clip(o.yaw_rate + rng.normal(0.0, TURN_SIGMA_RAD_S * np.sqrt(dt)), -1.5, 1.5))
        x, y = o.x + o.speed * np.cos(heading) * dt, o.y + o.speed * np.sin(heading) * dt
        if not _in_room(self.settings, max_angle, x, y):
            tx, ty = _room_point(self.settings, max_angle, rng)
            heading = float(np.arctan2(ty - o.y, tx - o.x))
            x, y = o.x + o.speed * np.cos(heading) * dt, o.y + o.speed * np.sin(heading) * dt
        return replace(o, x=float(x), y=float(y), heading=float(heading), yaw_rate=yaw_rate)

    def step(self) -> list[ObjectState]:
        """The objects of the current frame, then advances the scene by one frame period."""
        current = list(self.objects)
        self.objects = [self._walk(o, self.profile.frame_period_s) for o in self.objects]
        return current


def _wall(profile: RadarProfile, settings: SceneSettings, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(x, y, rcs) of one wall's scatterers, a back wall facing the radar or a side wall along the line of sight, and
    the wall as a mirror: (unit normal x, y, distance from the radar, bounce loss dB)."""
    max_r = profile.max_range
    lo, hi = settings.wall_range_m or (min(settings.range_m[1], 0.9 * max_r), 0.97 * max_r)
    distance = rng.uniform(lo, hi)
    spacing = profile.range_resolution / 2
    if rng.random() < 0.5:  # back wall: perpendicular to a ray near boresight
        normal = np.radians(rng.uniform(-0.4, 0.4) * profile.max_angle_deg)
        half = distance * np.tan(np.radians(profile.max_angle_deg))
        along = np.arange(-half, half, spacing)
        x = distance * np.sin(normal) + along * np.cos(normal)
        y = distance * np.cos(normal) - along * np.sin(normal)
        mirror = (np.sin(normal), np.cos(normal), distance)
    else:  # side wall at lateral offset, from near the radar to the far end
        side = rng.choice([-1.0, 1.0]) * distance * np.sin(np.radians(rng.uniform(0.5, 0.9) * profile.max_angle_deg))
        y = np.arange(abs(side) * 0.3 + 0.3, max_r, spacing)
        x = np.full(len(y), side)
        normal = np.pi / 2 * np.sign(side)
        mirror = (np.sign(side), 0.0, abs(side))
    incidence = np.arctan2(x, y) - normal  # between the line of sight and the wall's normal
    peak = rng.uniform(*WALL_PEAK_RCS_DBSM)
    rcs = peak + 10 * np.log10(np.cos(incidence) ** 8 + 1e-3) + rng.normal(0.0, 2.0, len(x))
    keep = np.hypot(x, y) < max_r * 0.99
    return x[keep], y[keep], rcs[keep], np.array([*mirror, rng.uniform(*WALL_BOUNCE_LOSS_DB)])


def indoor_clutter(profile: RadarProfile, settings: SceneSettings, rng: np.random.Generator) -> StaticClutter:
    """The static reflectors of one room (all at zero Doppler; the radar is static), its walls also as mirrors."""
    max_r = profile.max_range
    xs, ys, rcs, mirrors = [], [], [], []
    for _ in range(int(rng.integers(settings.walls[0], settings.walls[1] + 1))):
        for part, value in zip((xs, ys, rcs, mirrors), _wall(profile, settings, rng), strict=True):
            part.append(value)
    for _ in range(int(rng.integers(settings.furniture[0], settings.furniture[1] + 1))):
        n = int(rng.integers(3, 9))
        r = rng.uniform(0.4, 0.95) * max_r
        a = np.radians(rng.uniform(-0.9, 0.9) * profile.max_angle_deg)
        xs.append(r * np.sin(a) + rng.uniform(-0.3, 0.3, n))
        ys.append(r * np.cos(a) + rng.uniform(-0.3, 0.3, n))
        rcs.append(rng.uniform(*FURNITURE_RCS_DBSM, n))
    n_diffuse = int(rng.integers(60, 100))
    r = max_r * np.sqrt(rng.uniform(0.01, 0.95, n_diffuse))
    a = np.radians(rng.uniform(-80, 80, n_diffuse))
    xs += [r * np.sin(a), np.array([0.0])]
    ys += [r * np.cos(a), np.array([0.1])]
    rcs += [rng.uniform(*DIFFUSE_RCS_DBSM, n_diffuse), np.array([rng.uniform(*COUPLING_RCS_DBSM)])]
    return StaticClutter(np.concatenate(xs), np.concatenate(ys), np.concatenate(rcs), np.array(mirrors).reshape(-1, 4))
