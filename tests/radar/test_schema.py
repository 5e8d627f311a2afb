import pytest

from radar.profiles import CARRADA, SMALL
from radar.schema import SchemaMismatch, check_schema, cube_schema, schema_differences


def test_identical_schemas_match_and_differences_are_named():
    assert schema_differences(cube_schema(CARRADA), cube_schema(CARRADA)) == []
    diffs = schema_differences(cube_schema(CARRADA), cube_schema(SMALL))
    assert any(d.startswith("shape: expected [256, 256, 64], got [128, 128, 32]") for d in diffs)
    assert any(d.startswith("range.step: expected 0.1953125 m, got 0.390625") for d in diffs)
    with pytest.raises(SchemaMismatch, match="content: expected 'complex', got 'log_power_db'"):
        check_schema(cube_schema(CARRADA), cube_schema(CARRADA, "log_power_db"))


def test_same_bins_from_another_radar_differ_by_fingerprint():
    import dataclasses

    other = dataclasses.replace(CARRADA, n_tx=1, n_rx=8)  # same cube and bins, another array
    diffs = schema_differences(cube_schema(CARRADA), cube_schema(other))
    assert len(diffs) == 1 and diffs[0].startswith("profile fingerprint")


def test_garbage_is_not_a_schema():
    assert schema_differences(cube_schema(SMALL), {"shape": [1]}) == ["not a radarseg.cube-schema description"]
    with pytest.raises(ValueError, match="content"):
        cube_schema(SMALL, "dB")
