"""GET /v1/streams/{id}/recording: a stream's frames as MCAP (Foxglove's schemas), MCAP of ROS 2 messages and Rerun's
.rrd, read back with the formats' own readers and equal to what the stream's frames answered (objects, track ids,
classes of the labelled voxels)."""

from __future__ import annotations

import io

import numpy as np
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from radar.simulate import simulate_sequence
from service.encoding import decode_array
from tests.pipelines.recordings.test_recordings_read_back import ProtobufDecoderFactory
from tests.service.conftest import NPY, npy_bytes


def _messages(payload: bytes, factory) -> dict[str, list]:
    topics: dict[str, list] = {}
    for _, channel, message, decoded in make_reader(io.BytesIO(payload), decoder_factories=[factory]
                                                    ).iter_decoded_messages():
        topics.setdefault(channel.topic, []).append((message.log_time, decoded))
    return topics


def test_a_streams_recording_holds_its_frames(make_settings, client_for):
    client = client_for(make_settings())
    stream = client.post("/v1/streams").json()["id"]
    answers = {}
    for seq, frame in zip((0, 1, 3), simulate_sequence("small", 3, seed=4), strict=True):  # a gap at 2
        r = client.post(f"/v1/streams/{stream}/frames?seq={seq}&outputs=objects,voxels&encoding=zlib",
                        content=npy_bytes(frame.cube), headers=NPY)
        assert r.status_code == 200, r.text
        answers[seq] = r.json()
    r = client.get(f"/v1/streams/{stream}/recording?format=mcap")
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-mcap"
    assert r.headers["content-disposition"] == f'attachment; filename="stream-{stream}.mcap"'
    topics = _messages(r.content, ProtobufDecoderFactory())
    period_ns = topics["/radar/points"][1][0] - topics["/radar/points"][0][0]
    assert [t for t, _ in topics["/radar/points"]] == [0, period_ns, 3 * period_ns]
    for (_, cloud), (_, scene), answer in zip(topics["/radar/points"], topics["/radar/objects"], answers.values(),
                                              strict=True):
        classes = np.frombuffer(cloud.data, np.uint8).reshape(-1, cloud.point_stride)[:, 20]  # class_id at 20
        voxels = decode_array(answer["voxels"]["array"])
        np.testing.assert_array_equal(np.sort(classes), np.sort(voxels[:, 3]))
        metadata = [{kv.key: kv.value for kv in entity.metadata} for entity in scene.entities]
        assert [int(m["track_id"]) for m in metadata] == [o["track_id"] for o in answer["objects"]]
        assert [int(m["class_id"]) for m in metadata] == [o["class_id"] for o in answer["objects"]]
    ros2 = client.get(f"/v1/streams/{stream}/recording?format=ros2")
    tracks = _messages(ros2.content, Ros2DecoderFactory())["/radar/tracks"]
    for (_, message), answer in zip(tracks, answers.values(), strict=True):
        ids = [int.from_bytes(bytes(t.uuid.uuid)[8:], "big") for t in message.tracks]
        assert ids == [o["track_id"] for o in answer["objects"]]
    rrd = client.get(f"/v1/streams/{stream}/recording?format=rrd")
    assert rrd.status_code == 200 and rrd.content[:4] == b"RRF2"  # Rerun's file header


def test_recording_refusals(make_settings, client_for):
    client = client_for(make_settings())
    missing = client.get("/v1/streams/" + "0" * 32 + "/recording")
    assert missing.status_code == 404
    stream = client.post("/v1/streams").json()["id"]
    empty = client.get(f"/v1/streams/{stream}/recording")
    assert empty.status_code == 404 and empty.json()["error"] == "no_recording"
    assert client.get(f"/v1/streams/{stream}/recording?format=bag").status_code == 422
    assert client.delete(f"/v1/streams/{stream}").status_code == 204
    assert client.app.state.service.stream_recordings.bytes == 0
