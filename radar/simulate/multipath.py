"""Multipath ghosts of moving objects off a room's flat surfaces (walls), by the image method.

Indoors a walker's echo also comes back by way of the walls. Two kinds of path matter for a radar whose TX and RX
sit together:

- **one bounce** (radar -> object -> wall -> radar, and the same path reversed, equal in length, so the two add in
  phase): it appears at the mean of the direct range ``r`` and the image's range ``r'``, with the mean of the two
  radial velocities, between the two directions (placed at the mean of their sines, where a small virtual array
  that sends one way and receives the other puts it), attenuated by one reflection;
- **two bounces** (radar -> wall -> object -> wall -> radar): exactly the object's mirror image behind the wall,
  at ``r'`` with the image's radial velocity, attenuated by two reflections.

Both are further from the radar than the object and move with it, at the image's radial velocity or the mean of
the two: weak movers beyond a real one, as a recorded indoor frame shows (docs/guides/indoor-scenes.md). Ghosts are
not labelled: a segmentation label marks the object itself, so they are background the networks learn to leave
alone.
"""

from __future__ import annotations

import numpy as np

from radar.profiles import RadarProfile
from radar.simulate.fmcw import Scatterers

MAX_RANGE_SHARE = 0.97  # ghosts beyond this share of the radar's range are dropped (they would fold back)


def _mirrored(s: Scatterers, normal: np.ndarray, distance: float) -> tuple[np.ndarray, ...]:
    """Positions and velocities of ``s`` mirrored in the plane ``normal . p = distance``."""
    nx, ny = normal
    offset = s.x * nx + s.y * ny - distance
    along = s.vx * nx + s.vy * ny
    return s.x - 2 * offset * nx, s.y - 2 * offset * ny, s.vx - 2 * along * nx, s.vy - 2 * along * ny


def multipath_ghosts(profile: RadarProfile, objects: list[Scatterers], mirrors: np.ndarray,
                     rng: np.random.Generator) -> Scatterers:
    """The one- and two-bounce ghosts of every object's scatterers off every mirror (rows ``nx, ny, d, loss_db``,
    see :class:`radar.simulate.scene.StaticClutter`). Scatterers on the far side of a mirror make none."""
    parts = []
    limit = MAX_RANGE_SHARE * profile.max_range
    for nx, ny, distance, loss_db in np.asarray(mirrors, dtype=float).reshape(-1, 4):
        normal = np.array([nx, ny])
        bounce = 10 ** (loss_db / 20)
        for s in objects:
            inside = s.x * nx + s.y * ny < distance
            if not inside.any():
                continue
            direct = Scatterers(s.x[inside], s.y[inside], s.vx[inside], s.vy[inside], s.amplitude[inside])
            image = Scatterers(*_mirrored(direct, normal, distance), direct.amplitude)
            r, r_image = direct.range_m, image.range_m
            # two bounces: the mirror image itself
            twice = Scatterers(image.x, image.y, image.vx, image.vy,
                               direct.amplitude * bounce**2 * (r / r_image) ** 2)
            # one bounce, both ways round: at the mean range and radial velocity, between the two directions
            r_once = (r + r_image) / 2
            sin_once = np.clip((direct.sin_theta + image.sin_theta) / 2, -1.0, 1.0)
            cos_once = np.sqrt(1 - sin_once**2)
            v_once = (direct.radial_velocity + image.radial_velocity) / 2
            once = Scatterers(r_once * sin_once, r_once * cos_once, v_once * sin_once, v_once * cos_once,
                              2 * direct.amplitude * bounce * (r / r_once) ** 2)
            for ghost in (once, twice):
                keep = ghost.range_m < limit
                phase = np.exp(2j * np.pi * rng.random(int(keep.sum())))  # a path of its own length: its own phase
                parts.append(Scatterers(ghost.x[keep], ghost.y[keep], ghost.vx[keep], ghost.vy[keep],
                                        ghost.amplitude[keep] * phase))
    return Scatterers.concat(parts)
