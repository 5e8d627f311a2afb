"""Each recording of ``radarseg export recording`` read back with its format's own readers (mcap's reader with
protobuf's decoder for Foxglove's schemas, mcap_ros2's decoder for the ROS 2 messages, Rerun's chunk reader and
command line) and compared with the predictions store: classes, positions within float32 rounding, track ids,
timestamps one frame period apart."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

from tests.pipelines.recordings.expected import COLUMN, expected_frames

FLOAT32 = {"rtol": 1e-6, "atol": 1e-5}
_NUMPY_OF_FOXGLOVE = {1: "u1", 2: "u1", 3: "<u2", 4: "<i2", 5: "<u4", 6: "<i4", 7: "<f4", 8: "<f8"}
_NUMPY_OF_ROS = {1: "i1", 2: "u1", 3: "<i2", 4: "<u2", 5: "<i4", 6: "<u4", 7: "<f4", 8: "<f8"}


class ProtobufDecoderFactory(DecoderFactory):
    """protobuf's own message classes, built from the FileDescriptorSet each schema carries."""

    def decoder_for(self, message_encoding, schema):
        if message_encoding != "protobuf" or schema is None or schema.encoding != "protobuf":
            return None
        pool = descriptor_pool.DescriptorPool()
        for file in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
            pool.Add(file)
        message_class = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
        return message_class.FromString


def _packed(data: bytes, fields, stride: int, numpy_of: dict[int, str], type_of) -> np.ndarray:
    dtype = np.dtype({"names": [f.name for f in fields], "formats": [numpy_of[type_of(f)] for f in fields],
                      "offsets": [f.offset for f in fields], "itemsize": stride})
    return np.frombuffer(data, dtype)


def _decoded(path: Path, factory) -> dict[str, list]:
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        for _, channel, message, decoded in make_reader(f, decoder_factories=[factory]).iter_decoded_messages():
            by_topic.setdefault(channel.topic, []).append((message.log_time, decoded))
    return by_topic


def _check_points(points: np.ndarray, frame, x, y) -> None:
    np.testing.assert_allclose(points["x"], x, **FLOAT32)
    np.testing.assert_allclose(points["y"], y, **FLOAT32)
    np.testing.assert_allclose(points["velocity"], frame.velocity, **FLOAT32)
    np.testing.assert_array_equal(points["class_id"], frame.class_id)
    assert np.isfinite(points["log_power"]).all()  # the store's source (the recording) was read
    for class_id in np.unique(frame.class_id):  # a point's track is one of its class's objects' tracks
        tracks_of_class = set(frame.track_ids[frame.objects[:, COLUMN["class_id"]] == class_id].tolist()) or {0}
        assert set(points["track_id"][frame.class_id == class_id].tolist()) <= tracks_of_class


def test_foxglove_mcap_decodes_with_its_schemas_and_equals_the_store(exported):
    check_foxglove(exported)


def check_foxglove(exported) -> None:
    frames, class_names = expected_frames(exported["store"])
    topics = _decoded(exported["mcap"], ProtobufDecoderFactory())
    assert sorted(topics) == ["/radar/objects", "/radar/points", "/radar/ra_image", "/radar/rd_image"]
    assert all(len(messages) == len(frames) for messages in topics.values())
    assert frames[1].time_ns - frames[0].time_ns > 0 and len({f.time_ns for f in frames}) == len(frames)
    for frame, (log_time, cloud), (_, scene), (_, ra), (_, rd) in zip(
            frames, *(topics[t] for t in ("/radar/points", "/radar/objects", "/radar/ra_image", "/radar/rd_image")),
            strict=True):
        assert log_time == frame.time_ns == cloud.timestamp.seconds * 10**9 + cloud.timestamp.nanos
        points = _packed(cloud.data, cloud.fields, cloud.point_stride, _NUMPY_OF_FOXGLOVE, lambda f: f.type)
        _check_points(points, frame, frame.x, frame.y)
        assert len(scene.entities) == len(frame.objects)
        for entity, row, track_id in zip(scene.entities, frame.objects, frame.track_ids, strict=True):
            meta = {kv.key: kv.value for kv in entity.metadata}
            assert int(meta["class_id"]) == row[COLUMN["class_id"]] and int(meta["track_id"]) == track_id
            assert float(meta["score"]) == row[COLUMN["score"]]
            (cube,) = entity.cubes
            np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y],
                                       row[[COLUMN["x"], COLUMN["y"]]], **FLOAT32)
            assert entity.texts[0].text.startswith(class_names[int(row[COLUMN["class_id"]])])
            assert len(entity.arrows) == 1
        for image, mask in ((ra, frame.ra_mask), (rd, frame.rd_mask)):
            assert image.encoding == "rgb8" and (image.height, image.width) == mask.shape
            pixels = np.frombuffer(image.data, np.uint8).reshape(image.height, image.width, 3)[::-1]
            labelled = mask > 0  # class colours are not grey; unlabelled cells are grey dB
            assert (pixels[~labelled].max(axis=1) == pixels[~labelled].min(axis=1)).all()
            assert (pixels[labelled].max(axis=1) != pixels[labelled].min(axis=1)).all()


def test_foxglove_mcap_carries_the_class_names(exported):
    with open(exported["mcap"], "rb") as f:
        (metadata,) = list(make_reader(f).iter_metadata())
    assert json.loads(metadata.metadata["class_names"]) == expected_frames(exported["store"])[1]


def test_ros2_mcap_decodes_with_mcap_ros2_and_equals_the_store(exported):
    check_ros2(exported)


def check_ros2(exported) -> None:
    frames, _ = expected_frames(exported["store"])
    with open(exported["ros2"], "rb") as f:
        reader = make_reader(f, decoder_factories=[Ros2DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        schemas = {s.name: s.encoding for s in reader.get_summary().schemas.values()}
    assert schemas == {"radar_msgs/msg/RadarTracks": "ros2msg", "sensor_msgs/msg/PointCloud2": "ros2msg"}
    topics = _decoded(exported["ros2"], Ros2DecoderFactory())
    for frame, (log_time, tracks), (_, cloud) in zip(frames, topics["/radar/tracks"], topics["/radar/points"],
                                                     strict=True):
        assert log_time == frame.time_ns == tracks.header.stamp.sec * 10**9 + tracks.header.stamp.nanosec
        points = _packed(bytes(cloud.data), cloud.fields, cloud.point_step, _NUMPY_OF_ROS, lambda f: f.datatype)
        assert cloud.width == len(points) and not cloud.is_bigendian
        _check_points(points, frame, frame.y, -frame.x)  # ROS axes: x forward, y left
        assert len(tracks.tracks) == len(frame.objects)
        for track, row, track_id in zip(tracks.tracks, frame.objects, frame.track_ids, strict=True):
            uuid = bytes(track.uuid.uuid)
            assert uuid[:8] == b"radarseg" and int.from_bytes(uuid[8:], "big") == track_id
            assert track.classification == 32000 + row[COLUMN["class_id"]]
            np.testing.assert_allclose([track.position.x, track.position.y], [row[COLUMN["y"]], -row[COLUMN["x"]]],
                                       **FLOAT32)


def _rerun_columns(path: Path, entity: str, *names: str) -> list[tuple]:
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            empty = [[] for _ in range(batch.num_rows)]  # a frame without points or objects has no extra fields
            rows += list(zip(*(batch.column(name).to_pylist() if name in batch.schema.names else empty
                               for name in ("frame", *names)), strict=True))
    return sorted(rows, key=lambda row: row[0])


def test_rerun_recording_reads_back_with_rerun_and_equals_the_store(exported):
    check_rerun(exported)


def check_rerun(exported) -> None:
    frames, class_names = expected_frames(exported["store"])
    period_ns = frames[1].time_ns - frames[0].time_ns
    points = _rerun_columns(exported["rrd"], "/radar/points", "Points3D:positions", "Points3D:class_ids", "track_id")
    objects = _rerun_columns(exported["rrd"], "/radar/objects", "Boxes3D:centers", "Boxes3D:class_ids", "track_id")
    ra = _rerun_columns(exported["rrd"], "/radar/ra_labels", "SegmentationImage:buffer")
    assert len(points) == len(objects) == len(ra) == len(frames)
    for frame, (tick, positions, class_ids, _), (_, centres, object_classes, tracks), (_, (buffer,)) in zip(
            frames, points, objects, ra, strict=True):
        assert tick * period_ns == frame.time_ns
        positions = np.array(positions, np.float64).reshape(-1, 3)
        np.testing.assert_allclose(positions[:, 0], frame.x, **FLOAT32)
        np.testing.assert_allclose(positions[:, 1], frame.y, **FLOAT32)
        np.testing.assert_array_equal(class_ids, frame.class_id)
        np.testing.assert_allclose(np.array(centres).reshape(-1, 3)[:, :2],
                                   frame.objects[:, [COLUMN["x"], COLUMN["y"]]], **FLOAT32)
        np.testing.assert_array_equal(object_classes, frame.objects[:, COLUMN["class_id"]])
        np.testing.assert_array_equal(tracks, frame.track_ids)
        np.testing.assert_array_equal(np.frombuffer(bytes(buffer), np.uint8).reshape(frame.ra_mask.shape)[::-1],
                                      frame.ra_mask)
    from rerun.chunk import RrdReader

    (context,) = [c for c in RrdReader(exported["rrd"]).stream().to_chunks()
                  if c.entity_path == "/radar" and "AnnotationContext:context" in c.to_record_batch().schema.names]
    entries = context.to_record_batch().column("AnnotationContext:context").to_pylist()[0][0]
    assert [entry["class_description"]["info"]["label"] for entry in entries] == class_names


def test_rerun_command_line_verifies_the_recording(exported):
    rerun = Path(sys.executable).parent / "rerun"
    done = subprocess.run([str(rerun), "rrd", "verify", str(exported["rrd"])], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    assert "verified without error" in done.stdout + done.stderr


@pytest.mark.slow
def test_a_segment_batch_stores_recordings_equal_it(segmented):
    """The same checks on what segment-batch wrote (a tiny model's predictions of a simulated recording, tracked)."""
    check_foxglove(segmented)
    check_ros2(segmented)
    check_rerun(segmented)
