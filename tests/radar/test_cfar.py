"""CFAR centres (radar/cfar.py): the non-learned seed source that can stand in for the detector."""

import numpy as np
import pytest

from radar.cfar import CfarConfig, cfar_centres
from radar.profiles import SMALL
from radar.simulate import SimulatorConfig, simulate_frame
from radar.simulate.scene import ObjectState


def _easy_frame(x, y, heading, speed, class_name="car", seed=0):
    class_id = SMALL.class_names.index(class_name) + 1
    state = ObjectState(track_id=1, class_id=class_id, class_name=class_name, x=x, y=y, heading=heading,
                        speed=speed, yaw_rate=0.0, rcs_dbsm=15.0, gait_phase=0.0)
    return simulate_frame(SMALL, [state], None, t=0.0, rng=np.random.default_rng(seed),
                          config=SimulatorConfig(clutter=False))


@pytest.mark.parametrize("method", ["ca", "os"])
def test_cfar_finds_single_moving_objects(method):
    for i, (x, y, heading, speed) in enumerate([(0.0, 15.0, np.pi / 2, 6.0), (-6.0, 25.0, -np.pi / 2, 5.0),
                                                 (8.0, 30.0, np.pi / 3, 8.0)]):
        frame = _easy_frame(x, y, heading, speed, seed=i)
        (obj,) = frame.objects
        centres = cfar_centres(frame.log_power(), SMALL, CfarConfig(method=method))
        assert len(centres) >= 1
        cx, cy = SMALL.xy(centres.range_bin[0], centres.angle_bin[0])
        assert np.hypot(cx - obj.centre_x, cy - obj.centre_y) < 3.0
        assert abs(centres.doppler_bin[0] - obj.doppler_bin) < 3.0
        assert np.all(np.diff(centres.score) <= 0)


def test_cfar_on_noise_alone_finds_little():
    frame = simulate_frame(SMALL, [], None, t=0.0, rng=np.random.default_rng(3), config=SimulatorConfig(clutter=False))
    assert len(cfar_centres(frame.log_power(), SMALL)) <= 2
