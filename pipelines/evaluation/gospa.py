"""GOSPA: the generalised optimal sub-pattern assignment metric between the true objects and a tracker's
estimates of one frame (Rahmathullah, Garcia-Fernandez and Svensson, 2017), with alpha = 2.

For truth positions X, estimates Y, a cut-off ``c`` (m) and an order ``p``::

    GOSPA(X, Y) = ( min over assignments g of  sum_{(i, j) in g} d(x_i, y_j)^p  +  c^p / 2 * (|X| + |Y| - 2 |g|) )^(1/p)

with ``d`` the Euclidean distance in x-y (m) and only pairs closer than ``c`` assigned (a pair at ``c`` or
farther costs as much as a missed object and a false one). With alpha = 2 the sum splits into localisation (the
assigned pairs' ``d^p``), missed objects and false estimates (``c^p / 2`` each); the metric is in metres. Pinned to
Stone Soup's ``GOSPAMetric`` on a fixed example (tests/pipelines/evaluation/test_gospa.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment


@dataclass(frozen=True)
class Gospa:
    """GOSPA of one frame: the metric (m), its three parts (m^p: they sum to ``distance ** p``) and their counts."""

    distance: float
    localisation: float
    missed: float
    false: float
    n_assigned: int
    n_missed: int
    n_false: int


def gospa(truth_xy: np.ndarray, estimate_xy: np.ndarray, *, c: float, p: float = 1.0) -> Gospa:
    """GOSPA (alpha = 2) between ``truth_xy`` (N, 2) and ``estimate_xy`` (M, 2), positions in metres; cut-off
    ``c`` (m, > 0) and order ``p`` (>= 1)."""
    if not (np.isfinite(c) and c > 0):
        raise ValueError(f"c must be a finite distance > 0 m, got {c!r}")
    if not (np.isfinite(p) and p >= 1):
        raise ValueError(f"p must be a finite number >= 1, got {p!r}")
    truth_xy = np.asarray(truth_xy, np.float64).reshape(-1, 2)
    estimate_xy = np.asarray(estimate_xy, np.float64).reshape(-1, 2)
    half_penalty = c**p / 2
    n_truth, n_estimates = len(truth_xy), len(estimate_xy)
    localisation, n_assigned = 0.0, 0
    if n_truth and n_estimates:
        d = np.hypot(truth_xy[:, None, 0] - estimate_xy[None, :, 0], truth_xy[:, None, 1] - estimate_xy[None, :, 1])
        # a pair at c or farther is worth exactly a miss plus a false estimate: capping there keeps the optimum
        rows, cols = linear_sum_assignment(np.minimum(d, c) ** p)
        close = d[rows, cols] < c
        localisation, n_assigned = float(np.sum(d[rows, cols][close] ** p)), int(close.sum())
    n_missed, n_false = n_truth - n_assigned, n_estimates - n_assigned
    missed, false = half_penalty * n_missed, half_penalty * n_false
    return Gospa(distance=float((localisation + missed + false) ** (1 / p)), localisation=localisation,
                 missed=missed, false=false, n_assigned=n_assigned, n_missed=n_missed, n_false=n_false)
