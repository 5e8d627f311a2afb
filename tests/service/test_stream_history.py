"""A stream's earlier frames for a detector that reads them (service/streams/history.py), and through the service."""

from __future__ import annotations

import numpy as np
import pytest

from models.erasenet.model import EraseNet
from radar import transforms
from radar.simulate import simulate_sequence
from service.settings import ModelSpec
from service.streams.history import StreamHistory
from tests.conftest import save_tiny_checkpoints
from tests.service.conftest import NPY, npy_bytes


def _frame(value: float) -> np.ndarray:
    return np.full((4, 4, 2), value, np.float32)


def test_consecutive_frames_only_the_last_n_kept_and_memory_bounded():
    history = StreamHistory(max_bytes=3 * 4 * 4 * 2 * 2)  # three float16 frames
    key = ("acme", "s1")
    assert history.earlier(key, 0, 2) == [None, None]
    for seq in (0, 1, 2):
        history.keep(key, seq, _frame(seq), n=2)
    latest, before = history.earlier(key, 3, 2)
    assert latest.dtype == np.float32 and latest[0, 0, 0] == 2 and before[0, 0, 0] == 1
    assert history.bytes == 2 * 4 * 4 * 2 * 2  # frame 0 dropped: frame 3 reads 2 and 1 only
    assert history.earlier(key, 5, 2) == [None, None]  # a gap: frames 4 and 3 were never kept
    assert history.earlier(key, 4, 2)[0] is None and history.earlier(key, 4, 2)[1][0, 0, 0] == 2
    other = ("acme", "s2")
    history.keep(other, 0, _frame(7), n=2)
    history.keep(other, 1, _frame(8), n=2)  # 4 frames > 3: the least recently used stream goes
    assert history.earlier(key, 3, 2) == [None, None] and history.bytes == 2 * 4 * 4 * 2 * 2
    history.forget(other)
    assert history.bytes == 0 and history.earlier(other, 2, 1) == [None]
    with pytest.raises(ValueError, match="max_bytes"):
        StreamHistory(-1)


def test_a_history_model_reads_the_streams_previous_frame(make_settings, client_for, tmp_path):
    made = save_tiny_checkpoints(None, tmp_path / "ckpt", ("detector_history", "segmenter"), mixed_labels=False)
    spec = ModelSpec(name="hist", detector=made["detector_history"], segmenter=made["segmenter"],
                     score_threshold=0.0, max_objects=1)
    client = client_for(make_settings(models=[spec]))
    cubes = [frame.cube for frame in simulate_sequence("small", 4, seed=31)]
    stream_id = client.post("/v1/streams", json={"model": "hist"}).json()["id"]
    answers = []
    for seq in (0, 1, 3):  # frame 2 skipped: frame 3 has no earlier frame kept
        answer = client.post(f"/v1/streams/{stream_id}/frames?seq={seq}&outputs=objects",
                             content=npy_bytes(cubes[seq]), headers=NPY)
        assert answer.status_code == 200, answer.text
        answers.append(answer.json())
    assert [a["history_frames"] for a in answers] == [0, 1, 0]
    net = EraseNet.from_checkpoints(made["detector_history"], made["segmenter"], score_threshold=0.0,
                                    max_objects=1)
    previous = transforms.log_power(cubes[0]).astype(np.float16).astype(np.float32)  # kept as float16
    with_history = net.segment(cubes[1], history=[previous]).centres.score
    alone = net.segment(cubes[1]).centres.score
    assert abs(float(with_history[0]) - float(alone[0])) > 1e-6
    assert answers[1]["objects"][0]["score"] == pytest.approx(float(with_history[0]), rel=1e-5)
    assert client.delete(f"/v1/streams/{stream_id}").status_code == 204


def test_a_single_cube_model_reads_no_history(make_settings, client_for):
    client = client_for(make_settings())
    stream_id = client.post("/v1/streams").json()["id"]
    cube = next(iter(simulate_sequence("small", 1, seed=31))).cube
    for seq in (0, 1):
        answer = client.post(f"/v1/streams/{stream_id}/frames?seq={seq}", content=npy_bytes(cube), headers=NPY)
        assert answer.status_code == 200 and answer.json()["history_frames"] == 0
