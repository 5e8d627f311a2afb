import numpy as np
import pytest

from radar.centres import Centres
from radar.doppler import DopplerRefinement, refine_doppler
from radar.profiles import SMALL
from radar.simulate import point_target_cube, simulate_sequence
from radar.transforms import log_power


def _point_target(doppler_bin: float, range_m: float = 20.0, angle_deg: float = 5.0):
    """Log power of one point target at an exact Doppler bin, and its (range, angle) bins."""
    cube = point_target_cube("small", range_m, angle_deg, float(SMALL.velocity_mps(doppler_bin)), seed=3)
    return log_power(cube), float(SMALL.range_bin(range_m)), float(SMALL.angle_bin(angle_deg))


@pytest.mark.parametrize("offset", [-1.6, -0.8, 0.9, 1.7])
def test_an_offset_estimate_moves_to_the_true_bin_of_a_point_target(offset):
    true_bin = 11.0
    lp, range_bin, angle_bin = _point_target(true_bin)
    detected = Centres.from_bins([[range_bin, angle_bin, true_bin + offset]], score=[0.9])
    refined = refine_doppler(lp, detected)
    assert abs(refined.doppler_bin[0] - true_bin) < 0.5, refined.doppler_bin
    assert refined.range_bin[0] == range_bin and refined.angle_bin[0] == angle_bin and refined.score[0] == 0.9


def test_the_doppler_axis_wraps():
    lp, range_bin, angle_bin = _point_target(0.0)  # the target sits on bin 0; the estimate is below it
    refined = refine_doppler(lp, Centres.from_bins([[range_bin, angle_bin, SMALL.n_doppler - 1.2]]))
    error = (refined.doppler_bin[0] - 0.0 + SMALL.n_doppler / 2) % SMALL.n_doppler - SMALL.n_doppler / 2
    assert abs(error) < 0.5 and 0 <= refined.doppler_bin[0] < SMALL.n_doppler


def test_a_target_outside_the_window_does_not_pull_the_estimate():
    lp = np.zeros(SMALL.shape, np.float32)
    lp[40, 60, 19:22] = [30.0, 40.0, 30.0]  # a target on bin 20; nothing else above the floor
    estimate = 12.3
    refined = refine_doppler(lp, Centres.from_bins([[40, 60, estimate]]), noise_db=0.0)
    assert refined.doppler_bin[0] == pytest.approx(estimate)
    refined = refine_doppler(lp, Centres.from_bins([[40, 60, 19.4]]), noise_db=0.0)  # the target in the window
    assert refined.doppler_bin[0] == pytest.approx(20.0)


def test_refinement_brings_offset_true_centres_closer_to_the_labelled_doppler():
    rng = np.random.default_rng(0)
    before, after = [], []
    for frame in list(simulate_sequence("small", 6, seed=31))[::2]:
        objects = [o for o in frame.objects if o.n_voxels]
        truth = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in objects])
        noisy = truth.copy()
        noisy[:, 2] += rng.choice([-1.5, 1.5], len(truth))  # the detector's typical error and more
        refined = refine_doppler(frame.log_power(), Centres.from_bins(noisy))
        before.extend(np.abs(noisy[:, 2] - truth[:, 2]))
        after.extend(np.abs(refined.doppler_bin - truth[:, 2]))
    assert len(before) >= 3
    assert np.mean(after) < 0.6 * np.mean(before), (np.mean(before), np.mean(after))


def test_empty_centres_and_bad_arguments():
    lp = np.zeros(SMALL.shape, np.float32)
    empty = Centres.from_bins(np.zeros((0, 3)))
    assert len(refine_doppler(lp, empty)) == 0
    with pytest.raises(ValueError, match="doppler_bins"):
        DopplerRefinement(doppler_bins=-1)
    with pytest.raises(ValueError, match=r"\(R, A, D\)"):
        refine_doppler(lp[0], Centres.from_bins([[1, 2, 3]]))
