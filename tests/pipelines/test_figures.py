"""Frame pictures: a colour bar beside every view, and a note when a prediction is empty."""

from __future__ import annotations

import numpy as np
import pytest

import pipelines.figures as figures
from radar.profiles import get_profile


@pytest.fixture
def captured(monkeypatch):
    """The figures the plotting functions would save (still open), instead of PNG files."""
    saved = []
    monkeypatch.setattr(figures, "save_figure", lambda fig, path: saved.append(fig) or path)
    yield saved
    for fig in saved:
        figures.plt.close(fig)


def _texts(fig) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.texts]


def _colorbars(fig) -> int:
    return sum(ax.get_label() == "<colorbar>" for ax in fig.axes)


def test_truth_and_prediction_have_colour_bars_and_an_empty_prediction_says_so(captured, tmp_path):
    profile = get_profile("small")
    rng = np.random.default_rng(0)
    log_power = rng.normal(20, 3, profile.shape).astype(np.float32)
    ra_truth = np.zeros((profile.n_range, profile.n_angle), np.uint8)
    ra_truth[40:44, 60:64] = 1
    rd_truth = np.zeros((profile.n_range, profile.n_doppler), np.uint8)
    rd_truth[40:44, 10:12] = 1
    empty = (np.zeros_like(ra_truth), np.zeros_like(rd_truth))
    figures.plot_truth_vs_prediction(log_power, profile, (ra_truth, rd_truth), empty, tmp_path / "f.png",
                                     truth_objects=[("car", 1.0, 16.0, 2.0)], predicted_objects=[])
    (fig,) = captured
    assert _colorbars(fig) == 4  # RA and RD, truth and prediction rows
    assert _texts(fig).count("no detections") == 2 and "no labelled objects" not in _texts(fig)

    figures.plot_truth_vs_prediction(log_power, profile, (ra_truth, rd_truth), (ra_truth, rd_truth),
                                     tmp_path / "g.png", truth_objects=[("car", 1.0, 16.0, 2.0)],
                                     predicted_objects=[("car 0.90", 1.0, 16.0, 2.0)])
    assert "no detections" not in _texts(captured[1])

    figures.plot_prediction(log_power, profile, *empty, [], tmp_path / "h.png")
    assert _colorbars(captured[2]) == 2 and _texts(captured[2]).count("no detections") == 2
