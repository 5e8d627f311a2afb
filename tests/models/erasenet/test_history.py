"""ERASE-Net with a detector that reads the frame before: history through segment and detect, frozen or eager."""

import numpy as np
import pytest
import torch

from models.erasenet.model import EraseNet
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence
from tests.conftest import save_tiny_checkpoints


@pytest.fixture(scope="module")
def history_pair(tmp_path_factory):
    made = save_tiny_checkpoints(None, tmp_path_factory.mktemp("ckpt"), ("detector_history", "segmenter"),
                                 mixed_labels=False)
    return made["detector_history"], made["segmenter"]


@pytest.fixture(scope="module")
def frames():
    return [frame.log_power().astype(np.float32) for frame in simulate_sequence("small", 2, seed=3)]


def _outputs(net, cube, history):
    with torch.no_grad():
        inputs = {} if history is None else net._history_input(history)
        return {k: v.numpy() for k, v in net._run_detector(net._detector_input(cube), **inputs).items()}


def test_absent_history_is_the_single_cube_and_a_present_one_is_read(history_pair, frames):
    net = EraseNet.from_checkpoints(*history_pair, score_threshold=0.0)
    assert net.history_frames == 1
    previous, cube = frames
    alone = _outputs(net, cube, None)
    np.testing.assert_allclose(_outputs(net, cube, [None])["heatmap_logits"], alone["heatmap_logits"],
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(_outputs(net, cube, [])["heatmap_logits"], alone["heatmap_logits"],
                               rtol=1e-5, atol=1e-6)
    assert np.abs(_outputs(net, cube, [previous])["heatmap_logits"] - alone["heatmap_logits"]).max() > 0
    result = net.segment(cube, kind=InputKind.log_power, history=[previous])
    assert result.labels.shape == net.profile.shape and result.compute.detections == len(result.centres)
    assert len(net.detect(cube, score_threshold=0.0, history=[previous])) > 0


def test_the_frozen_history_graph_equals_the_eager_detector(history_pair, frames):
    frozen = EraseNet.from_checkpoints(*history_pair, score_threshold=0.0)
    eager = EraseNet.from_checkpoints(*history_pair, score_threshold=0.0, frozen_detector=False)
    previous, cube = frames
    for history in (None, [previous], [None]):
        got, expected = _outputs(frozen, cube, history), _outputs(eager, cube, history)
        for name in expected:
            np.testing.assert_allclose(got[name], expected[name], rtol=1e-4, atol=1e-4)


def test_history_is_checked(history_pair, tiny_checkpoints, frames):
    net = EraseNet.from_checkpoints(*history_pair)
    previous, cube = frames
    with pytest.raises(ValueError, match="2 earlier frames given, the detector reads 1"):
        net.segment(cube, kind=InputKind.log_power, history=[previous, previous])
    with pytest.raises(ValueError, match="earlier frame must have the cube's shape"):
        net.segment(cube, kind=InputKind.log_power, history=[previous[:, :, :8]])
    single = EraseNet.from_checkpoints(*tiny_checkpoints)
    assert single.history_frames == 0
    with pytest.raises(ValueError, match="reads one frame"):
        single.segment(cube, kind=InputKind.log_power, history=[previous])
