"""Extended-target scatterer models: every class of every preset as a few point scatterers with
micro-Doppler (swinging limbs, wheel rims) and frame-to-frame RCS fluctuation (docs/design.md section 3.1).

An object's state is its centre (x, y), heading and speed; a model places scatterers in the body
frame (``along`` the heading, ``across`` to its left), gives each a velocity (body velocity plus
micro-motion along the heading) and an RCS in dBsm. Only scatterers on faces turned towards the
radar are kept for box-shaped vehicles (self-occlusion).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ClassModel:
    """How one object class looks to the radar. Speeds in m/s, sizes in metres, RCS in dBsm."""

    kind: str  # "walker", "two_wheeler" or "box"
    length: float
    width: float
    rcs_dbsm: tuple[float, float]  # total RCS range of the object
    speed: tuple[float, float]
    wheel_radius: float = 0.0


# Keyed by class name so every preset's classes share one table (pedestrian == person).
CLASS_MODELS: dict[str, ClassModel] = {
    "pedestrian": ClassModel("walker", 0.3, 0.5, (-10.0, -6.0), (0.6, 2.2)),
    "person": ClassModel("walker", 0.3, 0.5, (-10.0, -6.0), (0.6, 2.2)),
    "cyclist": ClassModel("two_wheeler", 1.8, 0.6, (-2.0, 2.0), (2.5, 7.0), wheel_radius=0.35),
    "motorcycle": ClassModel("two_wheeler", 2.1, 0.8, (3.0, 7.0), (5.0, 15.0), wheel_radius=0.32),
    "car": ClassModel("box", 4.5, 1.8, (10.0, 20.0), (3.0, 12.0), wheel_radius=0.32),
    "truck": ClassModel("box", 10.0, 2.5, (20.0, 30.0), (3.0, 14.0), wheel_radius=0.5),
}


def class_model(class_name: str) -> ClassModel:
    try:
        return CLASS_MODELS[class_name]
    except KeyError:
        raise ValueError(f"no scatterer model for class {class_name!r}; known: {sorted(CLASS_MODELS)}") from None


@dataclass(frozen=True)
class BodyScatterers:
    """Scatterers in the body frame: positions (m), velocity along the heading (m/s), RCS share (dB)."""

    along: np.ndarray
    across: np.ndarray
    v_along: np.ndarray
    rcs_share_db: np.ndarray  # relative RCS of each scatterer; normalised to the object's total


def _walker(model: ClassModel, speed: float, t: float, gait_phase: float) -> BodyScatterers:
    # Torso, head, two arms and two legs; limbs swing sinusoidally at the gait frequency, legs
    # in anti-phase with each other and with the arm on the same side.
    gait_hz = 0.9 + 0.5 * speed
    phase = 2 * np.pi * gait_hz * t + gait_phase
    swing = np.array([0.0, 0.0, 1.0, -1.0, -1.0, 1.0])  # torso, head, arm L, arm R, leg L, leg R
    amp = np.array([0.0, 0.0, 0.6, 0.6, 1.2, 1.2]) * speed  # micro-Doppler amplitude, m/s
    v_along = speed + amp * swing * np.sin(phase)
    along = amp * swing * (-np.cos(phase)) / (2 * np.pi * gait_hz)
    across = np.array([0.0, 0.0, 0.22, -0.22, 0.1, -0.1])
    rcs = np.array([0.0, -9.0, -8.0, -8.0, -5.0, -5.0])
    return BodyScatterers(along, across, v_along, rcs)


def _two_wheeler(model: ClassModel, speed: float, t: float, gait_phase: float) -> BodyScatterers:
    # Rider, frame, and per wheel three rim points: top (2v), hub (v), bottom (0): the 0..2v spread.
    half = model.length / 2 - model.wheel_radius
    along = [0.0, 0.1]
    v_along = [speed, speed]
    rcs = [0.0, -2.0]
    for hub in (half, -half):
        along += [hub, hub, hub]
        v_along += [2 * speed, speed, 0.0]
        rcs += [-9.0, -6.0, -12.0]
    # pedalling / suspension: a small periodic component on the rider
    v_along[0] += 0.3 * speed * np.sin(2 * np.pi * 1.2 * t + gait_phase)
    n = len(along)
    return BodyScatterers(np.array(along), np.zeros(n), np.array(v_along), np.array(rcs))


def _box(model: ClassModel, speed: float, t: float, gait_phase: float) -> BodyScatterers:
    # Corners, bumper and side midpoints, and wheels (rim top moves at 2v); occlusion is applied later.
    hl, hw = model.length / 2, model.width / 2
    along = [hl, hl, -hl, -hl, hl, -hl, 0.0, 0.0]
    across = [hw, -hw, hw, -hw, 0.0, 0.0, hw, -hw]
    rcs = [3.0, 3.0, 3.0, 3.0, 0.0, 0.0, -2.0, -2.0]
    v_along = [speed] * 8
    n_side = max(1, int(round(model.length / 4.0)))  # trucks get more points along each side
    for i in range(1, n_side):
        pos = -hl + i * model.length / n_side
        for side in (hw, -hw):
            along.append(pos)
            across.append(side)
            rcs.append(-2.0)
            v_along.append(speed)
    wheel_x = hl - 0.18 * model.length
    for wx in (wheel_x, -wheel_x):
        for side in (hw, -hw):
            along.append(wx)
            across.append(side)
            rcs.append(-6.0)
            v_along.append(2 * speed * (0.5 + 0.5 * np.cos(2 * np.pi * 3.0 * t + gait_phase)))
    return BodyScatterers(np.array(along), np.array(across), np.array(v_along, dtype=float), np.array(rcs))


_BUILDERS = {"walker": _walker, "two_wheeler": _two_wheeler, "box": _box}


def object_scatterers(model: ClassModel, *, x: float, y: float, heading: float, speed: float,
                      rcs_dbsm: float, t: float, gait_phase: float, rng: np.random.Generator,
                      fluctuation_db: float) -> tuple[np.ndarray, ...]:
    """World-frame scatterers of one object at time ``t`` (s).

    ``heading`` is the direction of travel in radians from the +x axis. Returns arrays
    ``(x, y, vx, vy, rcs_dbsm)`` of shape (P,); the RCS of each scatterer fluctuates from frame to
    frame (log-normal, ``fluctuation_db`` std) and the visible ones share ``rcs_dbsm`` in total.
    """
    body = _BUILDERS[model.kind](model, speed, t, gait_phase)
    fwd = np.array([np.cos(heading), np.sin(heading)])
    left = np.array([-np.sin(heading), np.cos(heading)])
    px = x + body.along * fwd[0] + body.across * left[0]
    py = y + body.along * fwd[1] + body.across * left[1]
    keep = np.ones(len(px), bool)
    if model.kind == "box":
        # A scatterer on the box outline is visible when one of the faces it lies on turns
        # towards the radar (outward normal . direction to radar > 0).
        to_radar = -np.array([x, y]) / max(np.hypot(x, y), 1e-6)
        hl, hw = model.length / 2, model.width / 2
        faces = [(fwd, body.along >= hl - 1e-6), (-fwd, body.along <= -hl + 1e-6),
                 (left, body.across >= hw - 1e-6), (-left, body.across <= -hw + 1e-6)]
        keep[:] = False
        for normal, on_face in faces:
            if normal @ to_radar > 0:
                keep |= on_face
    share = body.rcs_share_db[keep] + rng.normal(0.0, fluctuation_db, keep.sum())
    share_lin = 10 ** (share / 10)
    rcs = rcs_dbsm + 10 * np.log10(share_lin / share_lin.sum())
    v = body.v_along[keep]
    return px[keep], py[keep], v * fwd[0], v * fwd[1], rcs
