"""A detector that reads earlier frames of the sequence (``history_frames``): it also runs on a single cube."""

import pytest
import torch

from models.detector.centre_detector import backbone_in_channels
from models.detector.inference import FrozenDetector
from models.registry import create_model


def _detector(history_frames: int):
    torch.manual_seed(0)
    return create_model("centre_detector_tiny", preset="small", doppler_channels=4,
                        history_frames=history_frames).eval()


def test_a_single_cube_is_a_history_of_absent_frames():
    detector = _detector(2)
    assert detector.backbone.stem[0].in_channels == backbone_in_channels(4, 2) == 4 + 2 + 2 * 5
    x = torch.randn(2, 32, 128, 128)
    earlier = torch.randn(2, 2, 32, 128, 128)
    with torch.no_grad():
        alone = detector(x)
        absent = detector(x, history=earlier, history_present=torch.zeros(2, 2, dtype=torch.bool))
        with_history = detector(x, history=earlier)
        second_only = detector(x, history=earlier, history_present=torch.tensor([[False, False], [True, False]]))
    for name in alone:
        torch.testing.assert_close(absent[name], alone[name])  # absent frames are masked out, whatever they hold
        torch.testing.assert_close(second_only[name][0], alone[name][0])
    logits = "heatmap_logits"  # (an untrained head's Doppler output can be constant)
    assert not torch.allclose(with_history[logits], alone[logits])
    assert not torch.allclose(second_only[logits][1], alone[logits][1])


def test_history_shapes_are_checked_and_a_one_frame_detector_refuses_history():
    x = torch.randn(1, 32, 128, 128)
    with pytest.raises(ValueError, match=r"expected history \(1, 2, 32, 128, 128\)"):
        _detector(2)(x, history=torch.randn(1, 1, 32, 128, 128))
    with pytest.raises(ValueError, match="reads one frame"):
        _detector(0)(x, history=torch.randn(1, 1, 32, 128, 128))
    with pytest.raises(ValueError, match="history_frames must be >= 0"):
        _detector(-1)


def test_the_frozen_form_of_a_history_detector_runs_single_cubes():
    detector = _detector(1)
    x = torch.randn(1, 32, 128, 128)
    frozen = FrozenDetector(detector, tuple(x.shape))
    with torch.no_grad():
        expected, got = detector(x), frozen(x)
    for name in expected:
        torch.testing.assert_close(got[name], expected[name], rtol=1e-4, atol=1e-5)
