"""Scene settings of a radar: what its simulated scenes hold, at the radar's own scale.

A profile file's optional ``[scene]`` table describes rooms instead of roads: where the objects are, how many of
each class and how fast they move, and the static clutter of a room (walls and furniture, extended reflectors at
zero Doppler). A radar that sees 6 m then gets scenes of 6 m::

    [scene]
    range_m = [1.0, 5.0]              # objects' distance from the radar (min, max)
    classes = {person = [1, 2]}       # objects of each class in a frame (min, max); others: none
    speed_mps = {person = [0.3, 1.4]} # walking speed of each class (default: the class model's)
    min_separation_m = 0.8            # between two objects
    walls = [1, 2]                    # wall segments (extended reflectors) per scene (min, max)
    wall_range_m = [4.0, 6.0]         # distance of the walls from the radar (default: beyond range_m)
    furniture = [2, 5]                # pieces of furniture per scene (min, max)

Without the table a radar gets the road scenes of the built-in presets (``radar/simulate/scene.py``), unchanged.
:func:`default_scene` is the table ``radarseg radar from-ti`` writes for a radar that sees less than the road
radars: people walking in a room that fills the radar's range.

:func:`radar_scale` is the other half of "at the radar's own scale": settings stated in metres for a road radar
of 50 m (region growing's search grid, the AP distance thresholds) shrink with a radar that sees less.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

REFERENCE_RANGE_M = 50.0  # the range of the radars (CARRADA, small) the metre-valued defaults were set for

SCENE_KEYS = ("range_m", "classes", "speed_mps", "min_separation_m", "walls", "wall_range_m", "furniture")


def radar_scale(profile: Any) -> float:
    """How much smaller than the 50 m road radars ``profile`` sees: ``min(1, max range / 50 m)``. 1 for every
    built-in preset (CARRADA and small see 50 m, NXP 200 m), 0.125 for a radar of 6.25 m."""
    return min(1.0, float(profile.max_range) / REFERENCE_RANGE_M)


@dataclass(frozen=True)
class SceneSettings:
    """An indoor scene: object distances, per-class counts and speeds, and the room's static reflectors."""

    range_m: tuple[float, float]
    classes: tuple[tuple[str, tuple[int, int]], ...]  # (class name, (min, max) per frame)
    speed_mps: tuple[tuple[str, tuple[float, float]], ...] = ()
    min_separation_m: float = 0.8
    walls: tuple[int, int] = (1, 2)
    wall_range_m: tuple[float, float] | None = None
    furniture: tuple[int, int] = (2, 5)

    def count_range(self, class_name: str) -> tuple[int, int]:
        return dict(self.classes).get(class_name, (0, 0))

    def speed_range(self, class_name: str) -> tuple[float, float] | None:
        return dict(self.speed_mps).get(class_name)

    def to_table(self) -> dict[str, Any]:
        """The ``[scene]`` table (what :func:`scene_from_table` reads back)."""
        table: dict[str, Any] = {
            "range_m": list(self.range_m), "classes": {name: list(c) for name, c in self.classes},
            "min_separation_m": self.min_separation_m, "walls": list(self.walls), "furniture": list(self.furniture)}
        if self.speed_mps:
            table["speed_mps"] = {name: list(s) for name, s in self.speed_mps}
        if self.wall_range_m is not None:
            table["wall_range_m"] = list(self.wall_range_m)
        return table


def default_scene(profile: Any, person: str = "pedestrian") -> SceneSettings | None:
    """Rooms at ``profile``'s scale for a radar that sees less than the 50 m road radars (None for one that sees
    as far: road scenes suit it): 1 to 3 people (class ``person``) walking at 0.3 to 1.4 m/s (at most 90 % of the
    radar's unambiguous velocity), from ``min(1 m, 16 %)`` to 88 % of its range, walls and furniture as the
    table's defaults. For a radar of 6.25 m: people at 1.0 to 5.5 m, the scenes of ``checkpoints/openradar-indoor``.
    """
    if radar_scale(profile) >= 1.0:
        return None
    reach = float(profile.max_range)
    fastest = min(1.4, 0.9 * float(profile.max_velocity))
    return SceneSettings(range_m=(round(min(1.0, 0.16 * reach), 2), round(0.88 * reach, 2)),
                         classes=((person, (1, 3)),), speed_mps=((person, (min(0.3, fastest), round(fastest, 2))),),
                         min_separation_m=0.6, walls=(1, 3), furniture=(2, 6))


def _pair(value: Any, what: str, *, integer: bool) -> tuple:
    kinds = (int,) if integer else (int, float)
    if not (isinstance(value, list) and len(value) == 2
            and all(isinstance(v, kinds) and not isinstance(v, bool) for v in value)):
        raise ValueError(f"{what} must be [min, max] {'integers' if integer else 'numbers'}, got {value!r}")
    lo, hi = value
    if not 0 <= lo <= hi:
        raise ValueError(f"{what} must be [min, max] with 0 <= min <= max, got {value!r}")
    return (int(lo), int(hi)) if integer else (float(lo), float(hi))


def _per_class(value: Any, what: str, class_names: tuple[str, ...], *, integer: bool) -> tuple:
    if not isinstance(value, dict) or not value:
        raise ValueError(f"{what} must be a table of class name = [min, max], got {value!r}")
    unknown = sorted(set(value) - set(class_names))
    if unknown:
        raise ValueError(f"{what} names class(es) {unknown} the profile does not have; its classes: "
                         f"{list(class_names)}")
    return tuple((name, _pair(value[name], f"{what}.{name}", integer=integer))
                 for name in class_names if name in value)


def scene_from_table(table: dict[str, Any], class_names: tuple[str, ...], max_range_m: float) -> SceneSettings:
    """Checked :class:`SceneSettings` of a ``[scene]`` table; ValueError naming the key otherwise."""
    unknown = sorted(set(table) - set(SCENE_KEYS))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in [scene]; expected {sorted(SCENE_KEYS)}")
    if "range_m" not in table or "classes" not in table:
        raise ValueError("[scene] needs range_m (objects' [min, max] distance) and classes (counts per class)")
    range_m = _pair(table["range_m"], "[scene] range_m", integer=False)
    if range_m[1] > max_range_m:
        raise ValueError(f"[scene] range_m reaches {range_m[1]:g} m, beyond the radar's {max_range_m:.3g} m")
    if range_m[0] <= 0:
        raise ValueError(f"[scene] range_m must start above 0 m, got {range_m[0]:g}")
    classes = _per_class(table["classes"], "[scene] classes", class_names, integer=True)
    if sum(hi for _, (_, hi) in classes) == 0:
        raise ValueError("[scene] classes: every count is 0; a scene needs at least one object")
    kwargs: dict[str, Any] = {}
    if "speed_mps" in table:
        kwargs["speed_mps"] = _per_class(table["speed_mps"], "[scene] speed_mps", class_names, integer=False)
    for key in ("walls", "furniture"):
        if key in table:
            kwargs[key] = _pair(table[key], f"[scene] {key}", integer=True)
    if "wall_range_m" in table:
        kwargs["wall_range_m"] = _pair(table["wall_range_m"], "[scene] wall_range_m", integer=False)
        if kwargs["wall_range_m"][0] <= 0:
            raise ValueError("[scene] wall_range_m must start above 0 m")
    if "min_separation_m" in table:
        value = table["min_separation_m"]
        if isinstance(value, bool) or not isinstance(value, int | float) or value < 0:
            raise ValueError(f"[scene] min_separation_m must be a number >= 0, got {value!r}")
        kwargs["min_separation_m"] = float(value)
    return SceneSettings(range_m=range_m, classes=classes, **kwargs)
