import numpy as np
import pytest

from radar.detections import Centres
from radar.profiles import SMALL
from radar.region_growing import RegionGrowingConfig, grow_regions, noise_level_db
from radar.simulate import simulate_sequence


@pytest.fixture(scope="module")
def frames():
    return list(simulate_sequence("small", 8, seed=21))[::2]


def _true_seeds(frame):
    return np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels])


def test_seeded_at_true_centres_covers_the_labelled_voxels(frames):
    recalls = [grow_regions(f.log_power(), _true_seeds(f), f.profile).recall(f.instances) for f in frames]
    assert np.mean(recalls) >= 0.95, recalls


def test_regions_respect_the_distance_and_intensity_thresholds(frames):
    config = RegionGrowingConfig(intensity_ratio=0.5, distance_m=4.0)
    cart_x, cart_y = SMALL.ra_cartesian
    for f in frames:
        lp = f.log_power()
        noise = noise_level_db(lp)
        regions = grow_regions(lp, _true_seeds(f), f.profile, config)
        assert len(regions) > 0
        for i, (r0, a0, d0) in enumerate(regions.seeds):
            own = regions.voxels[regions.seed_index == i]
            r, a, d = own.T
            dist = np.hypot(cart_x[r, a] - cart_x[r0, a0], cart_y[r, a] - cart_y[r0, a0])
            assert (dist <= config.distance_m + 1e-4).all()
            seed_db = lp[r0, a0, d0] - noise
            floor = noise + max(config.intensity_ratio * seed_db, config.min_snr_db)
            assert (lp[r, a, d] >= floor - 1e-4).all()


def test_visited_count_is_exact_on_a_hand_built_cube():
    lp = np.zeros(SMALL.shape, np.float32)
    lp[40, 60, 10:13] = 50.0  # a 3-voxel line along Doppler: the region
    lp[40, 61, 11] = 20.0  # a neighbour below half the seed: examined, rejected
    regions = grow_regions(lp, np.array([[40, 60, 11]]), SMALL,
                           RegionGrowingConfig(intensity_ratio=0.5, distance_m=3.0, seed_search=(0, 0, 0)),
                           noise_db=0.0)
    assert sorted(map(tuple, regions.voxels.tolist())) == [(40, 60, 10), (40, 60, 11), (40, 60, 12)]
    # 3 members + 2 at the line's ends + 4 sides x 3 voxels = 17 examined
    assert regions.visited == 17
    assert regions.mask().sum() == 3 and (regions.seed_index == 0).all()


def test_distance_threshold_stops_a_long_region():
    lp = np.zeros(SMALL.shape, np.float32)
    lp[10:120, 64, 16] = 40.0  # a ridge along range at broadside
    config = RegionGrowingConfig(intensity_ratio=0.5, distance_m=5.0, seed_search=(0, 0, 0))
    regions = grow_regions(lp, np.array([[60, 64, 16]]), SMALL, config, noise_db=0.0)
    ranges = SMALL.range_m(regions.voxels[:, 0])
    assert ranges.min() >= SMALL.range_m(60) - 5.0 - 1e-6 and ranges.max() <= SMALL.range_m(60) + 5.0 + 1e-6
    assert len(regions) == 2 * int(5.0 / SMALL.range_res) + 1


@pytest.mark.parametrize(("gap", "bridge", "joined"), [(1, 0, False), (2, 1, True), (3, 1, False), (4, 2, True),
                                                      (5, 2, False)])
def test_bridge_closes_gaps_of_up_to_twice_its_size(gap, bridge, joined):
    lp = np.zeros(SMALL.shape, np.float32)
    lp[60, 64, 5:10] = 40.0  # two blobs along Doppler, `gap` empty voxels apart
    lp[60, 64, 10 + gap:15 + gap] = 40.0
    config = RegionGrowingConfig(intensity_ratio=0.0, distance_m=4.0, seed_search=(0, 0, 0), bridge=bridge)
    regions = grow_regions(lp, np.array([[60, 64, 7]]), SMALL, config, noise_db=0.0)
    assert len(regions) == (10 if joined else 5)  # gap voxels themselves never join
    assert not regions.mask()[60, 64, 10:10 + gap].any()


def test_bridge_must_be_a_voxel_count():
    assert RegionGrowingConfig(bridge=True).bridge == 1
    for bad in (-1, 1.5):
        with pytest.raises(ValueError, match="bridge"):
            RegionGrowingConfig(bridge=bad)


def test_overlapping_regions_keep_the_first_seed_and_bad_input_is_refused():
    lp = np.zeros(SMALL.shape, np.float32)
    lp[50:60, 64, 16] = 40.0
    seeds = Centres.from_bins(np.array([[52, 64, 16], [57, 64, 16]]))
    regions = grow_regions(lp, seeds, SMALL, RegionGrowingConfig(distance_m=8.0, seed_search=(0, 0, 0)), noise_db=0.0)
    assert len(regions) == 10 and (regions.seed_index == 0).all()
    with pytest.raises(ValueError, match="shape"):
        grow_regions(lp[:10], seeds, SMALL)
    with pytest.raises(ValueError, match="finite"):
        grow_regions(lp, np.array([[np.nan, 1, 1]]), SMALL)
    with pytest.raises(ValueError, match="distance_m"):
        RegionGrowingConfig(distance_m=0)


def test_dilate6_equals_scipys_binary_dilation():
    from scipy import ndimage

    from radar.region_growing import SIX_CONNECTED, dilate6

    mask = np.random.default_rng(4).random((9, 7, 5)) > 0.85
    mask[0, 0, 0] = mask[-1, -1, -1] = True  # corners: nothing may wrap around
    for iterations in (1, 2, 3):
        expected = ndimage.binary_dilation(mask, structure=SIX_CONNECTED, iterations=iterations)
        assert np.array_equal(dilate6(mask, iterations), expected)
