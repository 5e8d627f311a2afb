import numpy as np
import pytest

from radar import transforms
from radar.adc import adc_to_rad
from radar.simulate import SimulatorConfig, simulate_sequence
from radar.simulate.fmcw import synthesize_adc
from radar.simulate.targets import class_model


@pytest.fixture(scope="module")
def multi_object_frames():
    """Small-preset frames with at least two objects (seeded, so always the same frames)."""
    frames = [f for f in simulate_sequence("small", 12, seed=3, sequence_index=0) if len(f.objects) >= 2]
    assert frames, "the seeded sequence should contain multi-object frames"
    return frames[:3]


def _object_powers(frame):
    """Each object's own noiseless power over the whole cube, through the full ADC + FFT chain."""
    p = frame.profile
    return np.stack([np.abs(adc_to_rad(p, synthesize_adc(p, s))) ** 2 for s in frame.extras["object_scatterers"]])


def test_every_labelled_voxel_satisfies_the_response_rule(multi_object_frames):
    config = SimulatorConfig()
    for frame in multi_object_frames:
        p = frame.profile
        powers = _object_powers(frame)
        floor = 10 ** ((p.noise_floor_db + config.label_snr_db) / 10)
        r, a, d = np.nonzero(frame.instances)
        owner = frame.instances[r, a, d].astype(int) - 1
        own = powers[owner, r, a, d]
        assert len(own) > 0
        assert (own >= floor * 0.999).all()
        peaks = powers.reshape(len(powers), -1).max(axis=1)
        assert (own >= peaks[owner] * 10 ** (-config.label_peak_db / 10) * 0.999).all()
        assert (own >= powers[:, r, a, d].max(axis=0) * 0.999).all()
        # and conversely: voxels that satisfy the rule are labelled (up to the window cut at -45 dB)
        best = powers.argmax(axis=0)
        best_power = powers.max(axis=0)
        rule = (best_power >= floor) & (best_power >= peaks[best] * 10 ** (-config.label_peak_db / 10))
        agree = (np.where(rule, best + 1, 0) == frame.instances).mean()
        assert agree > 0.9999


def test_instance_ids_agree_with_the_object_table(multi_object_frames):
    for frame in multi_object_frames:
        ids = set(np.unique(frame.instances)) - {0}
        assert ids <= {o.instance_id for o in frame.objects}
        for o in frame.objects:
            mask = frame.instances == o.instance_id
            assert mask.sum() == o.n_voxels
            assert (frame.labels[mask] == o.class_id).all()
            assert o.class_name == frame.profile.class_names[o.class_id - 1]
        assert ((frame.labels > 0) == (frame.instances > 0)).all()


def test_label_centres_lie_near_the_true_position(multi_object_frames):
    for frame in multi_object_frames:
        for o in frame.objects:
            if o.n_voxels == 0:
                continue
            t = np.radians(o.true_angle_deg)
            true_x, true_y = o.true_range_m * np.sin(t), o.true_range_m * np.cos(t)
            # labels cover the faces that the radar sees: within half the object's length + 1 m
            tolerance = class_model(o.class_name).length / 2 + 1.0
            assert np.hypot(o.centre_x - true_x, o.centre_y - true_y) < tolerance, o
            expected_doppler = frame.profile.doppler_bin(o.true_velocity_mps) % frame.profile.n_doppler
            err = abs(o.doppler_bin - expected_doppler) % frame.profile.n_doppler
            assert min(err, frame.profile.n_doppler - err) < 3.0, o


def test_same_seed_same_recording_different_seed_different():
    a = list(simulate_sequence("small", 3, seed=11))
    b = list(simulate_sequence("small", 3, seed=11))
    c = list(simulate_sequence("small", 3, seed=12))
    for fa, fb in zip(a, b, strict=True):
        assert np.array_equal(fa.cube, fb.cube) and np.array_equal(fa.instances, fb.instances)
        assert fa.objects == fb.objects
    assert not np.array_equal(a[0].cube, c[0].cube)


def test_scenes_move_objects_smoothly_and_keep_counts_in_range():
    from radar.profiles import get_profile
    from radar.simulate.scene import SceneGenerator, in_field_of_view

    for name in ("small", "nxp"):
        profile = get_profile(name)
        scene = SceneGenerator(profile, np.random.default_rng(5))
        lo, hi = profile.objects_per_frame
        steps = [scene.step() for _ in range(300)]
        counts = [len(objects) for objects in steps]
        assert min(counts) >= lo and max(counts) <= hi, name
        for prev, cur in zip(steps, steps[1:], strict=False):
            before = {o.track_id: o for o in prev}
            for o in cur:
                assert in_field_of_view(profile, o.x, o.y)
                if o.track_id in before:
                    b = before[o.track_id]
                    assert o.class_id == b.class_id
                    step = np.hypot(o.x - b.x, o.y - b.y)
                    assert step == pytest.approx(o.speed * profile.frame_period_s, rel=1e-6)
        assert len({o.track_id for objects in steps for o in objects}) > hi  # objects entered and left


def test_simulated_frames_follow_the_scene():
    frames = list(simulate_sequence("small", 4, seed=5))
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert all(1 <= len(f.objects) <= 4 for f in frames)
    assert {o.track_id for o in frames[0].objects} & {o.track_id for o in frames[-1].objects}


def test_rd_view_statistics_resemble_carradas():
    frame = next(simulate_sequence("carrada", 1, seed=2))
    rd = transforms.rd_view(frame.cube)
    assert 55.0 < rd.mean() < 61.0
    assert 2.0 < rd.std() < 7.0


def test_every_class_of_every_preset_is_simulated():
    from radar.profiles import PRESETS

    for name, profile in PRESETS.items():
        for class_name in profile.class_names:
            assert class_model(class_name).length > 0, name


def test_only_yields_the_same_frames_as_the_full_run():
    full = list(simulate_sequence("small", 5, seed=9, sequence_index=2))
    some = list(simulate_sequence("small", 5, seed=9, sequence_index=2, only=[1, 4]))
    assert [f.index for f in some] == [1, 4]
    for frame in some:
        assert np.array_equal(frame.cube, full[frame.index].cube)
        assert np.array_equal(frame.instances, full[frame.index].instances)
    with pytest.raises(ValueError, match="ascending"):
        list(simulate_sequence("small", 5, seed=9, only=[3, 1]))
