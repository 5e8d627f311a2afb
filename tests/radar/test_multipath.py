"""Multipath ghosts of indoor walkers (radar/simulate/multipath.py): where the image method puts them, that they
are weaker and further than the walker, unlabelled, and absent from road scenes and with ``multipath=False``."""

from __future__ import annotations

import numpy as np
import pytest

from radar.profiles import get_profile
from radar.simulate import SimulatorConfig, simulate_sequence
from radar.simulate.fmcw import Scatterers
from radar.simulate.multipath import multipath_ghosts
from tests.radar.test_scenes import indoor_profile


def one_point(x, y, vx, vy) -> Scatterers:
    return Scatterers(np.array([x]), np.array([y]), np.array([vx]), np.array([vy]), np.array([1.0 + 0j]))


def test_a_side_wall_mirrors_a_walker_by_the_image_method():
    profile = get_profile("docs/profiles/openradar_ti_2tx4rx.toml")
    walker = one_point(0.0, 3.0, 0.0, 0.5)  # 3 m ahead, receding at 0.5 m/s
    wall = np.array([[1.0, 0.0, 1.0, -10.0]])  # the plane x = 1 m, 10 dB lost per bounce
    ghosts = multipath_ghosts(profile, [walker], wall, np.random.default_rng(0))
    assert len(ghosts) == 2
    image_range = np.hypot(2.0, 3.0)  # the mirror image sits at x = 2 m
    once, twice = np.argsort(ghosts.range_m)
    assert ghosts.range_m[once] == pytest.approx((3.0 + image_range) / 2)
    assert ghosts.range_m[twice] == pytest.approx(image_range)
    assert ghosts.x[twice] == pytest.approx(2.0) and ghosts.y[twice] == pytest.approx(3.0)
    assert ghosts.radial_velocity[twice] == pytest.approx(0.5 * 3.0 / image_range)  # the image's radial speed
    assert ghosts.radial_velocity[once] == pytest.approx((0.5 + 0.5 * 3.0 / image_range) / 2)
    # one bounce: 2 paths in phase, 10 dB and the longer range; two bounces: 20 dB and the image's range
    assert abs(ghosts.amplitude[once]) == pytest.approx(2 * 10 ** (-10 / 20) * (3.0 / ((3.0 + image_range) / 2)) ** 2)
    assert abs(ghosts.amplitude[twice]) == pytest.approx(10 ** (-20 / 20) * (3.0 / image_range) ** 2)


def test_a_walker_behind_the_wall_makes_no_ghost():
    profile = get_profile("docs/profiles/openradar_ti_2tx4rx.toml")
    ghosts = multipath_ghosts(profile, [one_point(1.5, 3.0, 0.0, 0.5)], np.array([[1.0, 0.0, 1.0, -10.0]]),
                              np.random.default_rng(0))
    assert len(ghosts) == 0


def test_indoor_frames_carry_unlabelled_ghosts_beyond_the_walkers():
    profile = indoor_profile()
    with_ghosts = next(simulate_sequence(profile, 1, seed=7))
    without = next(simulate_sequence(profile, 1, seed=7, config=SimulatorConfig(multipath=False)))
    assert np.array_equal(with_ghosts.labels, without.labels)  # ghosts are background
    power, power_without = (10 * np.log10(np.abs(f.cube) ** 2 + 1) for f in (with_ghosts, without))
    strong = power > np.median(power_without) + 20  # 20 dB over the noise
    ghost_voxels = np.nonzero((power - power_without > 10) & strong)
    assert len(ghost_voxels[0]) > 50, "no voxel gained 10 dB from the walls' ghosts"
    nearest_walker = min(o.centre_range_bin for o in with_ghosts.objects)
    assert ghost_voxels[0].min() > nearest_walker  # ghosts come back later than the walker nearest the radar
    zero = profile.n_doppler // 2
    assert np.mean(np.abs(ghost_voxels[2] - zero) > 1) > 0.9  # they move: off zero Doppler


def test_road_scenes_have_no_mirrors():
    config = SimulatorConfig(multipath=False)
    a = next(simulate_sequence("small", 1, seed=11))
    b = next(simulate_sequence("small", 1, seed=11, config=config))
    assert np.array_equal(a.cube, b.cube)
