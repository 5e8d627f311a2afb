import numpy as np

from radar import transforms
from radar.input_kind import InputKind


def test_log_power_of_complex_and_magnitude():
    cube = np.array([[[3 + 4j, 0]]], dtype=np.complex64)
    np.testing.assert_allclose(transforms.log_power(cube), 10 * np.log10(np.array([[[26.0, 1.0]]])), rtol=1e-6)
    np.testing.assert_allclose(transforms.log_power(np.abs(cube)), transforms.log_power(cube), rtol=1e-6)


def test_views_reduce_the_right_axes():
    rng = np.random.default_rng(0)
    cube = (rng.normal(size=(4, 6, 5)) + 1j * rng.normal(size=(4, 6, 5))).astype(np.complex64)
    lp = transforms.log_power(cube)
    np.testing.assert_allclose(transforms.ra_view(cube), lp.max(axis=2), rtol=1e-6)
    power = np.abs(cube) ** 2
    np.testing.assert_allclose(transforms.rd_view(cube), 10 * np.log10(power.sum(axis=1) / 6 + 1), rtol=1e-5)
    np.testing.assert_allclose(transforms.rd_view(lp, kind=InputKind.log_power), transforms.rd_view(cube), rtol=1e-4)
    assert transforms.ad_view(cube).shape == (6, 5)


def test_projection_takes_the_majority_class_along_the_axis():
    labels = np.zeros((2, 3, 4), np.uint8)
    labels[0, 1, :3] = 2
    labels[0, 1, 3] = 1  # cell (0, 1): three voxels of class 2, one of class 1
    labels[1, 2, 0] = 3
    ra = transforms.project_ra(labels, num_classes=4)
    assert ra[0, 1] == 2 and ra[1, 2] == 3 and ra[0, 0] == 0
    rd = transforms.project_rd(labels, num_classes=4)
    assert rd[0, 0] == 2 and rd[0, 3] == 1 and rd[1, 0] == 3 and rd[1, 1] == 0


def test_log_power_equals_the_formula_to_float_rounding():
    rng = np.random.default_rng(2)
    cube = ((rng.normal(size=(8, 6, 4)) + 1j * rng.normal(size=(8, 6, 4))) * 300).astype(np.complex64)
    expected = 10.0 * np.log10(np.abs(cube.astype(np.complex128)) ** 2 + 1.0)
    for given in (cube, np.abs(cube), cube.astype(np.complex128)):
        result = transforms.log_power(given)
        assert result.dtype == np.float32 and result.shape == cube.shape
        np.testing.assert_allclose(result, expected, rtol=1e-5, atol=1e-5)


def test_projection_of_voxels_equals_the_projection_of_their_cube():
    rng = np.random.default_rng(3)
    shape, num_classes = (12, 10, 6), 4
    flat = rng.choice(np.prod(shape), size=300, replace=False)
    voxels = np.stack(np.unravel_index(flat, shape), axis=1)
    classes = rng.integers(0, num_classes, size=len(voxels)).astype(np.uint8)
    labels = np.zeros(shape, np.uint8)
    labels[tuple(voxels.T)] = classes
    for axis, dense in ((2, transforms.project_ra), (1, transforms.project_rd)):
        projected = transforms.project_voxels(voxels, classes, shape, axis, num_classes)
        assert np.array_equal(projected, dense(labels, num_classes))
