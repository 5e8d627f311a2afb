"""EraseNet refines its detector's Doppler from the cube (radar.doppler) by default; None keeps it."""

import numpy as np
import pytest
import torch

from models.erasenet.model import EraseNet
from models.registry import create_model
from radar import transforms
from radar.doppler import DOPPLER_REFINEMENT, refine_doppler
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence


@pytest.fixture(scope="module")
def frame():
    return list(simulate_sequence("small", 2, seed=3))[1]


def _net(**kwargs):
    torch.manual_seed(0)
    return EraseNet(create_model("centre_detector_tiny", preset="small"), create_model("minkunet_tiny", preset="small"),
                    "small", mean_db=60.0, std_db=8.0, score_threshold=0.0, max_objects=6, **kwargs)


def test_detections_carry_the_doppler_refined_from_the_cube(frame):
    log_power = transforms.log_power(frame.cube)
    raw = _net(doppler_refinement=None).segment(log_power, kind=InputKind.log_power).centres
    refined = _net().segment(log_power, kind=InputKind.log_power).centres
    assert _net().doppler_refinement == DOPPLER_REFINEMENT
    assert len(raw) == len(refined) == 6
    np.testing.assert_array_equal(refined.range_bin, raw.range_bin)
    np.testing.assert_array_equal(refined.score, raw.score)
    expected = refine_doppler(log_power, raw, DOPPLER_REFINEMENT).doppler_bin
    np.testing.assert_allclose(refined.doppler_bin, expected)
    assert not np.allclose(refined.doppler_bin, raw.doppler_bin)  # the refinement changed something


def test_given_centres_are_not_refined(frame):
    log_power = transforms.log_power(frame.cube)
    seeds = _net(doppler_refinement=None).segment(log_power, kind=InputKind.log_power).centres
    result = _net().segment(log_power, kind=InputKind.log_power, centres=seeds)  # e.g. true centres: used as given
    np.testing.assert_array_equal(result.centres.doppler_bin, seeds.doppler_bin)
