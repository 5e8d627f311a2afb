"""The CARRADA reader on a tiny fixture written in CARRADA's own layout and orientation."""

import json

import numpy as np
import pytest

from radar.errors import DataError
from radar.io.carrada import CarradaReader
from radar.profiles import CARRADA
from radar.simulate import point_target_cube

SEQ = "2019-09-16-12-52-12"
R, A, D = CARRADA.shape
TARGET = {"range_m": 20.0, "angle_deg": 14.0, "velocity_mps": 3.0}
CLASS_ID = 3  # car


def _target_bins():
    bins = (CARRADA.range_bin(TARGET["range_m"]), CARRADA.angle_bin(TARGET["angle_deg"]),
            CARRADA.doppler_bin(TARGET["velocity_mps"]))
    return tuple(int(round(float(b))) for b in bins)


def _write_root(root, *, magnitude_frame=True):
    """One sequence, frames 000000 (complex) and 000001 (magnitude), stored as CARRADA stores them:
    range descending in the RAD cube and RA masks, ascending in RD masks."""
    r0, a0, d0 = _target_bins()
    cube = point_target_cube(CARRADA, noise=True, seed=1, **TARGET)
    seq_dir = root / SEQ
    (seq_dir / "RAD_numpy").mkdir(parents=True)
    np.save(seq_dir / "RAD_numpy" / "000000.npy", cube[::-1])
    if magnitude_frame:
        np.save(seq_dir / "RAD_numpy" / "000001.npy", np.abs(cube[::-1]).astype(np.float32))
    rows = range(r0 - 2, r0 + 3)
    ra_points = [[R - 1 - r, a] for r in rows for a in range(a0 - 3, a0 + 4)]  # far-first rows
    rd_points = [[r, d] for r in rows for d in range(d0 - 1, d0 + 2)]
    annotations = {SEQ: {}}
    for name in (["000000", "000001"] if magnitude_frame else ["000000"]):
        dense = seq_dir / "annotations" / "dense" / name
        dense.mkdir(parents=True)
        ra = np.zeros((4, R, A), np.uint8)
        ra[0] = 1
        rd = np.zeros((4, R, D), np.uint8)
        rd[0] = 1
        for row, col in ra_points:
            ra[:, row, col] = 0
            ra[CLASS_ID, row, col] = 1
        for row, col in rd_points:
            rd[:, row, col] = 0
            rd[CLASS_ID, row, col] = 1
        np.save(dense / "range_angle.npy", ra)
        np.save(dense / "range_doppler.npy", rd)
        annotations[SEQ][name] = {"7": {
            "range_angle": {"dense": ra_points, "sparse": [], "box": [], "label": CLASS_ID},
            "range_doppler": {"dense": rd_points, "sparse": [], "box": [], "label": CLASS_ID},
        }}
    (root / "data_seq_ref.json").write_text(json.dumps({SEQ: {"split": "Test", "instances": ["7"]}}))
    (root / "annotations_frame_oriented.json").write_text(json.dumps(annotations))
    return root


@pytest.fixture(scope="module")
def carrada_root(tmp_path_factory):
    return _write_root(tmp_path_factory.mktemp("carrada"))


def test_reader_converts_to_the_rad_frame(carrada_root):
    reader = CarradaReader(carrada_root)
    assert reader.sequences() == [SEQ] and reader.split(SEQ) == "test" and len(reader) == 2
    r0, a0, d0 = _target_bins()
    frame = reader.read_frame(SEQ, 0)
    assert frame.cube.dtype == np.complex64 and frame.cube.shape == (R, A, D)
    peak = np.unravel_index(np.abs(frame.cube).argmax(), frame.cube.shape)
    assert abs(peak[0] - r0) <= 1 and abs(peak[1] - a0) <= 1 and abs(peak[2] - d0) <= 1
    # RAD labels: RA cell and RD cell both labelled -> 5 ranges x 7 angles x 3 Dopplers
    assert (frame.labels > 0).sum() == 5 * 7 * 3
    assert set(np.unique(frame.labels)) == {0, CLASS_ID}
    assert frame.labels[r0, a0, d0] == CLASS_ID and frame.labels[r0, a0, d0 + 5] == 0
    (obj,) = frame.objects
    assert obj.class_name == "car" and obj.n_voxels == 105
    assert obj.centre_range_bin == pytest.approx(r0, abs=0.5)
    assert obj.centre_angle_bin == pytest.approx(a0, abs=0.5)
    assert obj.doppler_bin == pytest.approx(d0, abs=0.01)
    # masks project back to what was annotated
    assert frame.ra_mask()[r0 - 2:r0 + 3, a0 - 3:a0 + 4].min() == CLASS_ID
    assert frame.rd_mask()[r0, d0] == CLASS_ID


def test_magnitude_cubes_are_read_as_magnitude(carrada_root):
    reader = CarradaReader(carrada_root)
    complex_frame, magnitude_frame = reader.read_frame(SEQ, 0), reader.read_frame(SEQ, 1)
    assert magnitude_frame.cube.dtype == np.float32
    np.testing.assert_allclose(magnitude_frame.log_power(), complex_frame.log_power(), rtol=1e-5, atol=1e-4)


def test_reader_errors_name_the_file(tmp_path):
    with pytest.raises(DataError, match="no such CARRADA root"):
        CarradaReader(tmp_path / "nowhere")
    root = _write_root(tmp_path / "root", magnitude_frame=False)
    (root / "data_seq_ref.json").write_text(json.dumps({SEQ: {"split": "Dev"}}))
    with pytest.raises(DataError, match="split 'Dev'"):
        CarradaReader(root)
    (root / "data_seq_ref.json").unlink()
    with pytest.raises(DataError, match="data_seq_ref.json: missing file"):
        CarradaReader(root)
    (root / "data_seq_ref.json").write_text(json.dumps({SEQ: {"split": "Train"}}))
    rad = root / SEQ / "RAD_numpy" / "000000.npy"
    cube = np.load(rad)
    cube[0, 0, 0] = np.inf
    np.save(rad, cube)
    with pytest.raises(DataError, match="NaN or Inf"):
        CarradaReader(root).read_frame(SEQ, 0)
    np.save(rad, cube[:, :, :32])
    with pytest.raises(DataError, match=r"expected \(256, 256, 64\)"):
        CarradaReader(root).read_frame(SEQ, 0)
    np.save(rad, np.zeros((R, A, D), np.complex64))
    (root / SEQ / "annotations" / "dense" / "000000" / "range_doppler.npy").unlink()
    with pytest.raises(DataError, match="range_doppler.npy: missing file"):
        CarradaReader(root).read_frame(SEQ, 0)


def test_bad_annotation_label_is_refused(tmp_path):
    root = _write_root(tmp_path / "root", magnitude_frame=False)
    ann_path = root / "annotations_frame_oriented.json"
    ann = json.loads(ann_path.read_text())
    ann[SEQ]["000000"]["7"]["range_angle"]["label"] = 9
    ann_path.write_text(json.dumps(ann))
    with pytest.raises(DataError, match="label 9"):
        CarradaReader(root).read_frame(SEQ, 0)
