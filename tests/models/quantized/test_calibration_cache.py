"""The int8 segmenter's calibration is kept (models.quantized.calibration_cache): a second load of the same pair reads
it back instead of calibrating, and segments as the calibrated model did; a stale or corrupt entry is never used."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from models.export import quantize
from models.quantized import calibration_cache
from models.quantized import erasenet as quantized_erasenet
from models.quantized.segmenter import Int8MinkUNet
from models.runtime import load_erasenet
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence

SEEDS = {"score_threshold": 0.0, "max_objects": 4}


@pytest.fixture
def calibrations(tmp_path, monkeypatch):
    """The cache in a folder of the test's own, two calibration frames, and a count of calibrations run."""
    monkeypatch.setenv("RADARSEG_INT8_CACHE", str(tmp_path / "int8"))
    monkeypatch.setattr(quantize, "CALIBRATION_FRAMES", 2)
    runs = []
    calibrate = quantized_erasenet.int8_segmenter

    def counted(*args, **kwargs):
        runs.append(1)
        return calibrate(*args, **kwargs)

    monkeypatch.setattr(quantized_erasenet, "int8_segmenter", counted)
    return tmp_path / "int8", runs


@pytest.fixture(scope="module")
def cube():
    return next(simulate_sequence("small", 1, seed=5)).cube


def test_a_second_load_reads_the_calibration_back(calibrations, tiny_checkpoints, cube):
    root, runs = calibrations
    first = load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 1 and len(list(root.glob("*.json"))) == 1
    second = load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 1  # read back, not calibrated
    assert second.precision == "int8" and isinstance(second.segmenter_form, Int8MinkUNet)
    assert second.segmenter_form.activation_scales and all(
        np.array_equal(a.numpy(), b.numpy())
        for a, b in zip(first.segmenter_form.activation_scales, second.segmenter_form.activation_scales, strict=True))
    a, b = first.segment(cube), second.segment(cube)
    assert len(a.regions) > 0 and np.array_equal(a.labels, b.labels)
    load_erasenet(*tiny_checkpoints, runtime="torch-int8", score_threshold=0.0, max_objects=2)
    assert len(runs) == 2 and len(list(root.glob("*.json"))) == 2  # other seeds, another ROI: its own calibration


def test_a_corrupt_or_stale_calibration_is_calibrated_again(calibrations, tiny_checkpoints, caplog):
    root, runs = calibrations
    load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    (path,) = root.glob("*.json")
    kept = json.loads(path.read_text())
    record = json.loads(path.read_text())
    record["ranges"]["activation_scales"][0][0] *= 2  # a changed value, its sha256 not
    path.write_text(json.dumps(record))
    with caplog.at_level(logging.WARNING, logger="models.quantized.erasenet"):
        load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 2 and "corrupt" in caplog.text
    assert json.loads(path.read_text()) == kept  # written anew
    path.write_text(path.read_text()[:-20])  # cut short
    load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 3 and json.loads(path.read_text()) == kept


def test_a_file_of_another_key_is_refused_as_stale(calibrations, tiny_checkpoints):
    root, _ = calibrations
    net = load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    (path,) = root.glob("*.json")
    key = json.loads(path.read_text())["key"]
    other = {**key, "segmenter_sha256": "0" * 64}
    assert calibration_cache.cache_path(other, root) != path
    fused = net.segmenter_form.fused
    assert calibration_cache.load(path, key, fused)[0] is not None
    loaded, problem = calibration_cache.load(path, other, fused)
    assert loaded is None and problem == "stale: calibrated for another segmenter_sha256"
    assert calibration_cache.load(root / "missing.json", key, fused) == (None, "none kept")


def test_a_given_calibration_is_keyed_by_its_frames(calibrations, tiny_checkpoints):
    from models.checkpoint import load_pair
    from models.export.export_cache import Int8Calibration

    detector, segmenter = load_pair(*tiny_checkpoints)
    net = load_erasenet(detector, segmenter, **SEEDS)
    given = Int8Calibration.simulated(net.profile, frames=2)
    key = quantized_erasenet.calibration_key(net, detector, segmenter, given)
    assert key["frames"]["frames_sha256"] == quantize.calibration_digest(given.cubes)
    changed = Int8Calibration((given.cubes[0] + 1.0, given.cubes[1]), given.description, given.methods)
    assert quantized_erasenet.calibration_key(net, detector, segmenter, changed) != key
    simulated = quantized_erasenet.calibration_key(net, detector, segmenter)
    assert simulated["frames"]["source"] == "simulated" and simulated["frames"]["frames"] == 2


def test_the_segmenter_form_is_attached_in_public(tiny_checkpoints, cube):
    net = load_erasenet(*tiny_checkpoints, **SEEDS)
    assert net.precision == "float" and net.segmenter_form is not None
    fused = net.segmenter_form
    calls = []

    def form(sparse):
        calls.append(len(sparse.feats))
        return fused(sparse)

    net.use_segmenter_form(form)
    assert net.segmenter_form is form and net.precision == "float"
    net.segment(cube, kind=InputKind.complex)
    assert calls and calls[0] > 0


def _reseal(path, record) -> None:
    """Write ``record`` sealed with this machine's key (what no one without the key can do)."""
    record["mac"] = calibration_cache._seal(record["key"], record["ranges"])
    path.write_text(json.dumps(record))


@pytest.fixture
def sealed(calibrations, tmp_path, monkeypatch):
    monkeypatch.setenv("RADARSEG_ONNX_CACHE_KEY_FILE", str(tmp_path / "secret" / "cache.key"))
    return calibrations


def test_a_tampered_calibration_is_never_used(sealed, tiny_checkpoints, caplog):
    """Scales x 1e4 with a recomputed sha256 were used silently (4 objects became 0): the file is sealed under a key
    outside the cache, so a tampered one is calibrated again."""
    import hashlib

    root, runs = sealed
    load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    (path,) = root.glob("*.json")
    kept = json.loads(path.read_text())
    record = json.loads(path.read_text())
    record["ranges"]["activation_scales"] = [[v * 1e4 for v in s] for s in record["ranges"]["activation_scales"]]
    record["sha256"] = hashlib.sha256(calibration_cache._canonical({"key": record["key"], "ranges": record["ranges"]})
                                      ).hexdigest()
    record["mac"] = hashlib.sha256(b"guess").hexdigest()
    path.write_text(json.dumps(record))
    with caplog.at_level(logging.WARNING, logger="models.quantized.erasenet"):
        load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 2 and "not sealed by this machine's cache key" in caplog.text
    assert json.loads(path.read_text()) == kept


def test_any_error_in_a_sealed_calibration_means_a_fresh_one(sealed, tiny_checkpoints, caplog):
    """A list of the wrong length under a valid seal crashed with IndexError; a 3 GB file was read whole."""
    root, runs = sealed
    load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    (path,) = root.glob("*.json")
    record = json.loads(path.read_text())
    record["ranges"]["activation_scales"] = record["ranges"]["activation_scales"][:-1]
    _reseal(path, record)
    with caplog.at_level(logging.WARNING, logger="models.quantized.erasenet"):
        net = load_erasenet(*tiny_checkpoints, runtime="torch-int8", **SEEDS)
    assert len(runs) == 2 and "activation scale vectors" in caplog.text
    net.segment(next(simulate_sequence("small", 1, seed=5)).cube)
    with path.open("r+b") as huge:
        huge.truncate(3 * 2**30)  # sparse: 3 GB at the cache path
    loaded, problem = calibration_cache.load(path, record["key"], net.segmenter_form.fused)
    assert loaded is None and "not read" in problem
