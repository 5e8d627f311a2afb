import numpy as np
import pytest
import torch

from models.capabilities import Stage
from models.checkpoint import Checkpoint, CheckpointError, load_checkpoint, save_checkpoint
from models.erasenet.detection import normalise_log_power
from models.erasenet.model import EraseNet
from models.registry import create_model
from radar import transforms
from radar.input_kind import InputKind
from radar.simulate import simulate_sequence


@pytest.fixture(scope="module")
def frame():
    return list(simulate_sequence("small", 2, seed=3))[1]


def _net(segmenter="minkunet_tiny", **kwargs):
    torch.manual_seed(0)
    return EraseNet(create_model("centre_detector_tiny", preset="small"), create_model(segmenter, preset="small"),
                    "small", mean_db=60.0, std_db=8.0, **kwargs)


@pytest.mark.parametrize("segmenter", ["minkunet_tiny", "spvcnn_tiny"])
def test_end_to_end_output_is_well_formed_and_consistent(frame, segmenter):
    net = _net(segmenter, score_threshold=0.0, max_objects=4)  # untrained: take the top 4 peaks
    result = net.segment(frame.cube)
    assert result.labels.shape == frame.profile.shape and result.labels.dtype == np.uint8
    assert len(result.centres) == 4 and len(result.regions) > 0
    # background outside the ROI, masks are the projections of the RAD cube
    outside = ~result.regions.mask()
    assert (result.labels[outside] == 0).all()
    assert np.array_equal(result.ra_mask, transforms.project_ra(result.labels, 4))
    assert np.array_equal(result.rd_mask, transforms.project_rd(result.labels, 4))
    compute = result.compute
    assert compute.segment_macs > 0 and compute.detect_macs == net.detector_macs()
    assert compute.roi_voxels == len(result.regions)
    assert compute.visited_points >= compute.roi_voxels
    assert list(compute.seconds) == ["transform", "detect", "grow", "segment", "project"]
    assert all(s > 0 for s in compute.seconds.values())
    for obj in result.objects:
        assert 1 <= obj.class_id < 4 and obj.n_voxels > 0
        assert obj.n_voxels <= (result.labels == obj.class_id).sum() + len(result.regions)
        assert obj.range_m == pytest.approx(np.hypot(obj.x, obj.y))


def test_log_power_input_gives_the_same_answer(frame):
    net = _net(score_threshold=0.0, max_objects=3)
    a = net.segment(frame.cube)
    b = net.segment(transforms.log_power(frame.cube), kind=InputKind.log_power)
    assert np.array_equal(a.labels, b.labels)


def test_float16_log_power_answers_as_its_float32_values(frame):
    # float16 log power is normalised in the one float32 buffer it is converted into, then converted again
    net = _net(score_threshold=0.0, max_objects=3)
    half = transforms.log_power(frame.cube).astype(np.float16)
    sent = half.copy()
    a = net.segment(half.astype(np.float32), kind=InputKind.log_power, keep_log_power=True, views=True)
    b = net.segment(half, kind=InputKind.log_power, keep_log_power=True, views=True)
    assert np.array_equal(half, sent)  # the caller's cube is left as it was
    assert np.array_equal(b.log_power, half.astype(np.float32)) and b.log_power.dtype == np.float32
    assert np.array_equal(a.labels, b.labels) and len(b.regions) > 0
    assert np.array_equal(a.centres.score, b.centres.score)
    assert all(np.array_equal(u, v) for u, v in zip(a.views, b.views, strict=True))
    assert list(b.compute.seconds) == ["transform", "detect", "grow", "segment", "project"]


def test_normalising_in_place_equals_the_formula(frame):
    log_power = torch.from_numpy(transforms.log_power(frame.cube))
    expected = (log_power - 60.0) * (1.0 / 8.0)
    assert torch.equal(normalise_log_power(log_power, 60.0, 8.0), expected)
    normalised = normalise_log_power(log_power, 60.0, 8.0, out=log_power)
    assert normalised.data_ptr() == log_power.data_ptr() and torch.equal(log_power, expected)


def test_no_detection_gives_an_all_background_answer(frame):
    result = _net(score_threshold=1.01).segment(frame.cube)  # a sigmoid never reaches 1.01
    assert len(result.centres) == 0 and len(result.regions) == 0 and result.objects == []
    assert not result.labels.any() and not result.ra_mask.any()
    assert result.compute.segment_macs == 0 and result.compute.detect_macs > 0


def test_wrong_shape_is_refused(frame):
    with pytest.raises(ValueError, match=r"shape \(128, 128, 32\)"):
        _net().segment(frame.cube[:64])


def test_checkpoints_rebuild_the_pipeline(tmp_path, frame):
    net = _net(score_threshold=0.0, max_objects=2)
    det = save_checkpoint(Checkpoint("centre_detector_tiny", {"preset": "small"}, net.detector.state_dict(), "small",
                                     ("background", "pedestrian", "cyclist", "car"), {"mean": 60.0, "std": 8.0}),
                          tmp_path / "det.pt")
    seg = save_checkpoint(Checkpoint("minkunet_tiny", {"preset": "small"}, net.segmenter.state_dict(), "small",
                                     ("background", "pedestrian", "cyclist", "car")), tmp_path / "seg.pt")
    loaded = EraseNet.from_checkpoints(det, seg, score_threshold=0.0, max_objects=2)
    assert np.array_equal(loaded.segment(frame.cube).labels, net.segment(frame.cube).labels)


def test_bad_checkpoints_are_refused(tmp_path):
    with pytest.raises(CheckpointError, match="no such checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="not a checkpoint") as junk:
        load_checkpoint(tmp_path / "junk.pt")
    assert "weights_only" not in str(junk.value)  # torch's advice (run the file's code) is not relayed
    torch.save({"format": "something-else"}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a radarseg checkpoint"):
        load_checkpoint(tmp_path / "other.pt")
    torch.save({"format": "radarseg.checkpoint", "payload": Checkpoint}, tmp_path / "code.pt")  # needs unpickling code
    with pytest.raises(CheckpointError, match="not a checkpoint") as code:
        load_checkpoint(tmp_path / "code.pt")
    assert "weights_only" not in str(code.value)


def test_checkpoints_say_what_they_are_and_roles_are_checked(tmp_path):
    net = _net()
    classes = ("background", "pedestrian", "cyclist", "car")
    det = save_checkpoint(Checkpoint("centre_detector_tiny", {"preset": "small"}, net.detector.state_dict(), "small",
                                     classes), tmp_path / "det.pt")
    seg = save_checkpoint(Checkpoint("minkunet_tiny", {"preset": "small"}, net.segmenter.state_dict(), "small",
                                     classes), tmp_path / "seg.pt")
    stored = torch.load(det, weights_only=True)
    assert (stored["stage"], stored["input_kind"]) == ("detector", "log_power_db")
    assert load_checkpoint(seg).stage == "segmenter"  # no extra["stage"]: derived from the architecture
    with pytest.raises(CheckpointError, match="swapped"):
        EraseNet.from_checkpoints(seg, det)
    with pytest.raises(CheckpointError, match="the same file"):
        EraseNet.from_checkpoints(det, det)
    with pytest.raises(CheckpointError, match="a detector checkpoint .*expected a segmenter checkpoint"):
        load_checkpoint(det, stage=Stage.SEGMENTER, option="--segmenter")


def test_given_centres_replace_the_detector(frame):
    from radar.centres import Centres

    seeds = Centres.from_bins(np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin]
                                        for o in frame.objects if o.n_voxels]))
    result = _net().segment(frame.cube, centres=seeds)
    assert result.compute.detect_macs == 0 and len(result.centres) == len(seeds)
    assert result.regions.recall(frame.instances) > 0.9
    seeded_only = EraseNet(None, _net().segmenter, "small", mean_db=60.0, std_db=8.0)  # seeds always given
    assert seeded_only.params["detector"] == 0 and seeded_only.detector_macs() == 0
    assert np.array_equal(seeded_only.segment(frame.cube, centres=seeds).labels, result.labels)
    with pytest.raises(ValueError, match="no detector"):
        seeded_only.segment(frame.cube)


def test_a_cube_described_for_another_radar_is_refused_by_name(frame):
    from radar.profiles import CARRADA
    from radar.schema import SchemaMismatch, cube_schema

    net = _net()
    with pytest.raises(SchemaMismatch, match=r"range.step: expected 0.390625 m, got 0.1953125"):
        net.segment(frame.cube, schema=cube_schema(CARRADA))
    assert net.segment(frame.cube, schema=net.schema()).labels.shape == frame.profile.shape


def test_frozen_detector_gives_the_eager_detectors_answer(frame):
    frozen, eager = _net(score_threshold=0.0, max_objects=3), _net(score_threshold=0.0, max_objects=3,
                                                                  frozen_detector=False)
    a, b = frozen.segment(frame.cube), eager.segment(frame.cube)
    np.testing.assert_allclose(a.centres.bins, b.centres.bins, atol=1e-4)
    assert np.array_equal(a.labels, b.labels)
    assert a.compute.segment_executed_macs >= a.compute.segment_macs > 0
