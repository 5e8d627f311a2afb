"""GOSPA (pipelines/evaluation/gospa.py) pinned to Stone Soup's GOSPAMetric on fixed examples, and its edge cases."""

from __future__ import annotations

import datetime

import numpy as np
import pytest
from stonesoup.metricgenerator.ospametric import GOSPAMetric
from stonesoup.types.state import State

from pipelines.evaluation.gospa import gospa

TRUTH = np.array([[0.0, 10.0], [3.0, 12.0], [-4.0, 20.0], [8.0, 30.0], [1.0, 40.0]])
ESTIMATES = np.array([[0.3, 10.4], [2.0, 12.5], [-4.0, 23.5], [8.1, 29.0], [15.0, 5.0], [1.5, 41.2]])


def stone_soup(truth: np.ndarray, estimates: np.ndarray, c: float, p: float) -> dict[str, float]:
    when = datetime.datetime(2026, 1, 1)
    metric = GOSPAMetric(c=c, p=p)
    states = [[State(np.array(xy).reshape(2, 1), timestamp=when) for xy in points] for points in (estimates, truth)]
    result, _ = metric.compute_gospa_metric(*states)
    return {k: float(v) for k, v in result.value.items()}


@pytest.mark.parametrize(("c", "p"), [(2.0, 1.0), (2.0, 2.0), (5.0, 1.0), (1.0, 3.0)])
@pytest.mark.parametrize(("n_truth", "n_estimates"), [(5, 6), (5, 2), (0, 3), (4, 0), (1, 1)])
def test_gospa_equals_stone_soups(c, p, n_truth, n_estimates):
    truth, estimates = TRUTH[:n_truth], ESTIMATES[:n_estimates]
    ours, theirs = gospa(truth, estimates, c=c, p=p), stone_soup(truth, estimates, c, p)
    assert ours.distance == pytest.approx(theirs["distance"], rel=1e-9, abs=1e-12)
    for part in ("localisation", "missed", "false"):
        assert getattr(ours, part) == pytest.approx(theirs[part], rel=1e-9, abs=1e-12), part


def test_the_example_by_hand():
    # c = 2, p = 1: pairs 0.5, 1.118, 1.005 and 1.581 m apart are assigned; (-4, 20)-(-4, 23.5) is 3.5 m > c:
    # one miss and one false; (15, 5) is false: 0.5 + 1.118 + 1.005 + 1.581 + 1 + 1 + 1
    result = gospa(TRUTH, ESTIMATES, c=2.0, p=1.0)
    assert (result.n_assigned, result.n_missed, result.n_false) == (4, 1, 2)
    expected = 0.5 + np.hypot(1.0, 0.5) + np.hypot(0.1, 1.0) + np.hypot(0.5, 1.2) + 3 * 1.0
    assert result.distance == pytest.approx(expected)
    assert result.localisation + result.missed + result.false == pytest.approx(result.distance)


def test_nothing_against_nothing_is_zero_and_bad_arguments_are_refused():
    assert gospa(np.zeros((0, 2)), np.zeros((0, 2)), c=2.0).distance == 0.0
    with pytest.raises(ValueError, match="c must be"):
        gospa(TRUTH, ESTIMATES, c=0.0)
    with pytest.raises(ValueError, match="p must be"):
        gospa(TRUTH, ESTIMATES, c=2.0, p=0.5)
