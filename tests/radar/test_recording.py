import json
import shutil

import numpy as np
import pytest

from radar.errors import DataError
from radar.io.npy import decode_npy
from radar.io.recording import Recording, RecordingWriter
from radar.profiles import SMALL
from radar.simulate import SIMULATOR_VERSION, SimulatorConfig, simulate_sequence


@pytest.fixture
def recording_copy(small_recording, tmp_path):
    dst = tmp_path / "rec"
    shutil.copytree(small_recording, dst)
    return dst


def test_recording_round_trips_frames_and_objects(small_recording):
    rec = Recording(small_recording)
    assert rec.sequences() == ["seq_000", "seq_001"] and len(rec) == 6
    frames = list(simulate_sequence("small", 3, seed=11, sequence_index=1))
    for original in frames:
        read = rec.read_frame("seq_001", original.index)
        assert np.array_equal(read.cube, original.cube)
        assert np.array_equal(read.labels, original.labels)
        assert np.array_equal(read.instances, original.instances)
        assert [o.to_dict() for o in read.objects] == [o.to_dict() for o in original.objects]
    meta = json.loads((small_recording / "recording.json").read_text())
    assert meta["preset"] == "small" and meta["radar"]["shape"] == [128, 128, 32]
    assert meta["classes"] == ["background", "pedestrian", "cyclist", "car"]
    assert meta["simulator"] == SimulatorConfig().stamp() == meta["source"]["simulator"]
    assert meta["simulator"]["version"] == SIMULATOR_VERSION


def test_a_recording_of_two_simulator_configurations_is_refused(tmp_path):
    with RecordingWriter(tmp_path / "rec", SMALL) as writer:
        writer.write(next(simulate_sequence("small", 1, seed=3)))
        other = next(simulate_sequence("small", 1, seed=3, sequence_index=1, config=SimulatorConfig(clutter=False)))
        with pytest.raises(ValueError, match="made by simulator"):
            writer.write(other)


def test_writer_refuses_to_overwrite_a_recording(small_recording):
    with pytest.raises(FileExistsError):
        RecordingWriter(small_recording, Recording(small_recording).profile)


def test_interrupted_write_leaves_no_finished_recording(tmp_path):
    out = tmp_path / "partial"
    with pytest.raises(RuntimeError), RecordingWriter(out, SMALL) as w:
        w.write(next(simulate_sequence("small", 1, seed=1)))
        raise RuntimeError("interrupted")
    assert (out / "seq_000" / "cubes" / "000000.npy").is_file()
    with pytest.raises(DataError, match="missing recording.json"):
        Recording(out)


def test_missing_cube_names_the_file(recording_copy):
    (recording_copy / "seq_000" / "cubes" / "000001.npy").unlink()
    with pytest.raises(DataError, match="000001.npy: missing file"):
        Recording(recording_copy).read_frame("seq_000", 1)


def test_wrong_shape_and_dtype_are_refused(recording_copy):
    path = recording_copy / "seq_000" / "cubes" / "000000.npy"
    np.save(path, np.zeros((64, 128, 32), np.complex64))
    with pytest.raises(DataError, match=r"shape \(64, 128, 32\), expected \(128, 128, 32\)"):
        Recording(recording_copy).read_frame("seq_000", 0)
    np.save(path, np.zeros((128, 128, 32), np.int16))
    with pytest.raises(DataError, match="dtype int16"):
        Recording(recording_copy).read_frame("seq_000", 0)


def test_nan_values_are_refused(recording_copy):
    path = recording_copy / "seq_000" / "cubes" / "000002.npy"
    cube = np.load(path)
    cube[3, 4, 5] = np.nan
    np.save(path, cube)
    with pytest.raises(DataError, match="NaN or Inf"):
        Recording(recording_copy).read_frame("seq_000", 2)


def test_truncated_cube_is_refused(recording_copy):
    path = recording_copy / "seq_001" / "cubes" / "000000.npy"
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(DataError, match="truncated"):
        Recording(recording_copy).read_frame("seq_001", 0)


def test_pickled_payload_is_refused(tmp_path):
    path = tmp_path / "evil.npy"
    np.save(path, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match="pickle"):
        decode_npy(path.read_bytes())
    with pytest.raises(DataError, match="magic"):
        decode_npy(b"not a numpy file at all")


def test_unknown_preset_and_bad_metadata(recording_copy):
    meta_path = recording_copy / "recording.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "preset": "radarx", "radar_file": None}))
    with pytest.raises(DataError, match="'radarx' is not a built-in preset"):
        Recording(recording_copy)
    schema = {**meta["schema"], "doppler": {**meta["schema"]["doppler"], "orientation": "positive approaching"}}
    meta_path.write_text(json.dumps({**meta, "schema": schema}))
    with pytest.raises(DataError, match="doppler.orientation: expected 'positive receding'"):
        Recording(recording_copy)
    meta_path.write_text("{not json")
    with pytest.raises(DataError, match="not valid JSON"):
        Recording(recording_copy)


def test_corrupt_labels_and_objects_name_the_file(recording_copy):
    (recording_copy / "seq_000" / "labels" / "000000.npz").write_bytes(b"garbage")
    with pytest.raises(DataError, match="000000.npz"):
        Recording(recording_copy).read_frame("seq_000", 0)
    (recording_copy / "seq_001" / "objects.json").write_text("[]")
    with pytest.raises(DataError, match="objects.json"):
        Recording(recording_copy).read_frame("seq_001", 1)
    with pytest.raises(DataError, match="unknown sequence"):
        Recording(recording_copy).read_frame("seq_999", 0)


def test_a_recording_of_a_radar_described_by_a_file_reads_back(tmp_path):
    from radar.profiles.files import profile_from_dict
    from tests.radar.profiles.test_files import CUSTOM

    profile = profile_from_dict(CUSTOM)
    frames = list(simulate_sequence(profile, 2, seed=1))
    with RecordingWriter(tmp_path / "lab", profile) as writer:
        for frame in frames:
            writer.write(frame)
    rec = Recording(tmp_path / "lab")
    assert rec.profile == profile
    assert np.array_equal(rec.read_frame("seq_000", 1).cube, frames[1].cube)


def test_adc_recordings_are_processed_on_read_into_the_same_cubes(tmp_path):
    from pipelines.datasets.record import simulate_recording

    out = simulate_recording(preset="small", sequences=1, frames=2, seed=11, out=tmp_path / "adc", progress=False,
                             adc=True)
    rec = Recording(out)
    assert rec.content == "adc" and not (out / "seq_000" / "cubes").exists()
    original = list(simulate_sequence("small", 2, seed=11))
    for frame in original:
        read = rec.read_frame("seq_000", frame.index)
        np.testing.assert_allclose(read.cube, frame.cube, rtol=1e-5, atol=1e-2)
        assert np.array_equal(read.labels, frame.labels)
    adc_bytes = sum(p.stat().st_size for p in (out / "seq_000" / "adc").iterdir())
    assert adc_bytes * 10 < 2 * original[0].cube.nbytes  # far smaller than the cubes
