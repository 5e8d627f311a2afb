import numpy as np
import pytest

from radar.profiles import SMALL
from radar.roi import roi_points, voxel_features


def test_features_are_position_velocity_and_normalised_power():
    lp = np.full(SMALL.shape, 60.0, np.float32)
    lp[40, 96, 20] = 80.0
    voxels = np.array([[40, 96, 20], [40, 64, 16]])
    feats = voxel_features(voxels, lp, SMALL, mean_db=60.0, std_db=10.0)
    x, y = SMALL.xy(40, 96)
    np.testing.assert_allclose(feats[0], [x / 50, y / 50, SMALL.velocity_mps(20) / SMALL.max_velocity, 2.0], rtol=1e-5)
    np.testing.assert_allclose(feats[1, [0, 2, 3]], [0.0, 0.0, 0.0], atol=1e-6)  # broadside, zero Doppler, mean power
    assert feats.dtype == np.float32 and feats.shape == (2, 4)


def test_bin_coordinates_are_the_voxels_themselves():
    lp = np.zeros(SMALL.shape, np.float32)
    voxels = np.array([[1, 2, 3], [4, 5, 6]])
    points = roi_points(voxels, lp, SMALL)
    assert np.array_equal(points.coords, voxels) and np.array_equal(points.inverse, [0, 1])


def test_cartesian_voxels_merge_collisions_and_keep_an_inverse():
    lp = np.zeros(SMALL.shape, np.float32)
    lp[100, 64, 5] = 10.0
    # two neighbouring angle bins at 39 m are 0.6 m apart laterally: one 1 m voxel, same Doppler
    voxels = np.array([[100, 64, 5], [100, 65, 5], [100, 64, 6]])
    points = roi_points(voxels, lp, SMALL, voxel_size_m=1.0)
    assert len(points) == 2
    assert points.inverse[0] == points.inverse[1] != points.inverse[2]
    assert points.features[points.inverse[0], 3] == pytest.approx(5.0)  # mean of 10 and 0
    with pytest.raises(ValueError, match="voxel_size_m"):
        roi_points(voxels, lp, SMALL, voxel_size_m=0.0)
