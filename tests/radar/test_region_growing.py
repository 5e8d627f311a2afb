import numpy as np
import pytest

from radar.centres import Centres
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


def _reference_grow_regions(log_power, seeds, profile, config, noise_db):
    """The original algorithm, written plainly: per seed a thresholded box, scipy's dilation, skimage's flood,
    visited voxels through a whole-cube mask, owners by np.unique (the first seed to reach a voxel keeps it)."""
    from scipy import ndimage
    from skimage.segmentation import flood

    from radar.region_growing import SIX_CONNECTED, _seed_voxels

    shape = profile.shape
    seed_voxels = _seed_voxels(seeds, log_power, config.seed_search)
    cart_x, cart_y = profile.ra_cartesian
    reach = int(np.ceil(config.distance_m / profile.range_res)) + 1
    members, owners, seen = [], [], np.zeros(shape, bool)
    for i, (r0, a0, d0) in enumerate(seed_voxels):
        r_lo, r_hi = max(0, r0 - reach), min(shape[0], r0 + reach + 1)
        disc = ((cart_x[r_lo:r_hi] - cart_x[r0, a0]) ** 2 + (cart_y[r_lo:r_hi] - cart_y[r0, a0]) ** 2
                <= config.distance_m**2)
        cols, rows = np.flatnonzero(disc.any(axis=0)), np.flatnonzero(disc.any(axis=1))
        a_lo, a_hi = max(0, cols.min() - 1), min(shape[1], cols.max() + 2)
        r_lo, r_hi = max(0, r_lo + rows.min() - 1), min(shape[0], r_lo + rows.max() + 2)
        disc = ((cart_x[r_lo:r_hi, a_lo:a_hi] - cart_x[r0, a0]) ** 2
                + (cart_y[r_lo:r_hi, a_lo:a_hi] - cart_y[r0, a0]) ** 2 <= config.distance_m**2)[:, :, None]
        seed_db = log_power[r0, a0, d0] - noise_db
        if seed_db < config.min_snr_db:
            seen[r0, a0, d0] = True
            continue
        threshold = noise_db + max(config.intensity_ratio * seed_db, config.min_snr_db)
        candidates = (log_power[r_lo:r_hi, a_lo:a_hi] >= threshold) & disc
        seed = (r0 - r_lo, a0 - a_lo, d0)
        if config.bridge:
            linked = ndimage.binary_dilation(candidates, SIX_CONNECTED, iterations=config.bridge) & disc
            region = flood(linked, seed, connectivity=1) & candidates
        else:
            region = flood(candidates, seed, connectivity=1)
        full = np.zeros(shape, bool)
        full[r_lo:r_hi, a_lo:a_hi] = region
        members.append(np.flatnonzero(full))
        owners.append(np.full(len(members[-1]), i))
        seen |= ndimage.binary_dilation(full, SIX_CONNECTED)
    flat, first = np.unique(np.concatenate(members or [np.zeros(0, int)]), return_index=True)
    voxels = np.stack(np.unravel_index(flat, shape), axis=1)
    return voxels, np.concatenate(owners or [np.zeros(0, int)])[first], int(seen.sum()) if seed_voxels.size else 0


def _assert_same_as_reference(log_power, seeds, profile, config):
    noise = noise_level_db(log_power)
    regions = grow_regions(log_power, seeds, profile, config)
    voxels, owners, visited = _reference_grow_regions(log_power, seeds, profile, config, noise)
    assert np.array_equal(regions.voxels, voxels)
    assert np.array_equal(regions.seed_index, owners)
    assert regions.visited == visited


@pytest.mark.parametrize("preset", ["small", "carrada"])
def test_grow_regions_equals_the_reference_algorithm(preset):
    frames = list(simulate_sequence(preset, 2, seed=9))
    rng = np.random.default_rng(3)
    configs = [RegionGrowingConfig.for_profile(preset), RegionGrowingConfig.for_profile(preset, bridge=1),
               RegionGrowingConfig.for_profile(preset, bridge=0, distance_m=5.0),
               RegionGrowingConfig(intensity_ratio=0.5, min_snr_db=3.0, bridge=2)]
    for frame in frames:
        lp = frame.log_power()
        true = _true_seeds(frame).astype(float)
        # true centres, jittered copies (overlapping regions), a seed in the noise, seeds at the cube's corners
        shape = np.array(lp.shape)
        seeds = np.concatenate([true, true + rng.normal(0, 2, true.shape), rng.uniform(0, shape, (1, 3)),
                                [[0, 0, 0], shape - 1]])
        for config in configs:
            _assert_same_as_reference(lp, seeds, frame.profile, config)


def test_grow_regions_equals_the_reference_when_regions_touch_every_face():
    lp = np.random.default_rng(5).normal(0.0, 1.0, SMALL.shape).astype(np.float32)
    lp[:, :, :] += 8.0 * (np.random.default_rng(6).random(SMALL.shape) > 0.4)  # dense candidates everywhere
    seeds = np.array([[0, 0, 0], [127, 127, 31], [64, 64, 16], [64, 66, 16], [3, 120, 30]])
    for bridge in (0, 1, 2):
        _assert_same_as_reference(lp, seeds, SMALL, RegionGrowingConfig(intensity_ratio=0.0, distance_m=6.0,
                                                                        min_snr_db=4.0, bridge=bridge))
    empty = grow_regions(lp, np.zeros((0, 3)), SMALL)
    assert len(empty) == 0 and empty.visited == 0


def test_flood6_equals_skimages_flood():
    from skimage.segmentation import flood

    from radar.region_growing import flood6

    rng = np.random.default_rng(8)
    for fill in (0.3, 0.6, 0.9):
        mask = rng.random((11, 9, 7)) < fill
        for seed in map(tuple, np.argwhere(mask)[::17]):
            assert np.array_equal(flood6(mask, seed), flood(mask, seed, connectivity=1))
    with pytest.raises(ValueError, match="inside the mask"):
        flood6(np.zeros((3, 3, 3), bool), (1, 1, 1))


def test_exact_median_equals_numpys_median_bit_for_bit():
    from radar.region_growing import exact_median

    rng = np.random.default_rng(11)
    samples = [rng.normal(50, 5, 135301).astype(np.float32), rng.normal(50, 5, 40000).astype(np.float32),
               np.sort(rng.exponential(3, 50001)).astype(np.float32),  # sorted: the probe is no random sample
               np.repeat(np.float32([1, 2, 3]), 20000), rng.normal(0, 1, 1000).astype(np.float32)]
    with_nan = rng.normal(0, 1, 50000).astype(np.float32)
    with_nan[7] = np.nan
    for values in [*samples, with_nan]:
        expected, got = np.median(values), exact_median(values)
        assert (np.isnan(expected) and np.isnan(got)) or got == expected
        assert got.dtype == expected.dtype
