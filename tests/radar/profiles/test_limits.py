"""Hostile radar profiles (radar.profiles.limits): NaN and infinity, sizes that would allocate gigabytes, a simulation
that never ends, nesting that overflows the parser's stack, and a tracker configuration that fails every frame are
each refused where the profile loads, with one line naming the key and the bound, before anything large is
allocated (measured with tracemalloc, which sees numpy's and Python's allocations)."""

from __future__ import annotations

import copy
import time
import tomllib
import tracemalloc
from pathlib import Path

import pytest

from pipelines.cli import main
from radar.profiles import profile_from_dict
from radar.profiles.files import ProfileError, load_profile_file
from radar.profiles.limits import MAX_NESTING, LimitError, nesting_depth
from radar.tracking import TrackerConfig  # noqa: F401 (imported before tracemalloc counts: the tracker check uses it)

SMALL = tomllib.loads((Path(__file__).resolve().parents[3] / "radar/profiles/presets/small.toml").read_text())


def _with(**changes) -> dict:
    """The small preset's file with ``table.key`` values replaced (``expect`` dropped: the sizes change)."""
    data = copy.deepcopy(SMALL)
    data.pop("expect", None)
    for dotted, value in changes.items():
        table, _, key = dotted.rpartition(".")
        (data.setdefault(table, {}) if table else data)[key] = value
    return data


HOSTILE = {  # what the profile says -> words of the refusal
    "noise floor NaN": (_with(**{"simulation.noise_floor_db": float("nan")}), "noise_floor_db = nan"),
    "chirp cycle infinite": (_with(**{"chirp.chirp_cycle_s": float("inf")}), "chirp_cycle_s = inf"),
    "angle_bins 1e8": (_with(**{"processing.angle_bins": 100_000_000}), "angle_bins = 100000000"),
    "n_tx 1e8": (_with(**{"array.n_tx": 100_000_000}), "n_tx = 100000000"),
    "objects 1e9": (_with(**{"simulation.objects_per_frame": [1, 1_000_000_000]}), "objects_per_frame"),
    "angle bins 65536": (_with(**{"processing.angle_bins": 65536}), "at most 4096"),
    "cube 4096^3": (_with(**{"chirp.samples_per_chirp": 4096, "chirp.chirps_per_frame": 4096,
                             "processing.angle_bins": 4096}), "voxels"),
    "confirm_hits 0": (_with(**{"tracking.confirm_hits": 0}), "confirm_hits"),
    "gate NaN": (_with(**{"tracking.gate_chi2": float("nan")}), "gate_chi2 = nan"),
    "max_misses 1e9": (_with(**{"tracking.max_misses": 1_000_000_000}), "max_misses = 1000000000"),
    "a class name of 1 MB": (_with(class_names=["car", "x" * 2**20]), "at most 128 characters"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_profiles_are_refused_with_one_line_before_any_large_allocation(case):
    data, words = HOSTILE[case]
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises((LimitError, ProfileError)) as refused:
            profile_from_dict(data, source="lab.toml")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    message = str(refused.value)
    assert words in message and (message.startswith("lab.toml") or "profile" in message), message
    assert "\n" not in message and len(message) < 400, message
    assert peak < 8 * 2**20, f"{peak / 2**20:.1f} MiB allocated before refusing {case}"
    assert time.perf_counter() - start < 2.0


def test_the_shipped_presets_are_within_the_bounds():
    for name in ("small", "carrada", "nxp"):
        path = Path(__file__).resolve().parents[3] / f"radar/profiles/presets/{name}.toml"
        assert load_profile_file(path).name == name


def test_a_profile_nested_100000_deep_is_one_line_not_a_recursion_error(tmp_path):
    path = tmp_path / "deep.toml"
    path.write_text("name = 'x'\nclass_names = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(LimitError, match=f"nested 100000 deep, at most {MAX_NESTING}"):
        load_profile_file(path)
    json_path = tmp_path / "deep.json"
    json_path.write_text('{"name": "x", "class_names": ' + "[" * 50_000 + "]" * 50_000 + "}")
    with pytest.raises(LimitError, match="nested"):
        load_profile_file(json_path)


def test_nesting_ignores_brackets_in_strings_and_comments():
    assert nesting_depth('a = "[[[[" # [[[[\nb = [[1], [2]]\n[table]\n') == 2
    assert nesting_depth("a = '''[[[\n[[['''\nb = \"\\\"[[\"") == 0


def test_the_cli_refuses_a_nan_profile_with_exit_2_and_one_line(tmp_path, capsys):
    path = tmp_path / "nan.toml"
    text = (Path(__file__).resolve().parents[3] / "radar/profiles/presets/small.toml").read_text()
    path.write_text(text.replace("noise_floor_db = 58.0", "noise_floor_db = nan"))
    assert main(["radar", "show", str(path)]) == 2
    err = capsys.readouterr().err
    assert "noise_floor_db = nan" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_checkpoint_whose_radar_is_too_large_is_refused_at_load(tiny_checkpoints, tmp_path):
    from models.checkpoint import load_checkpoint, save_checkpoint

    checkpoint = load_checkpoint(tiny_checkpoints[0])
    wide = _with(name="wide", **{"processing.angle_bins": 65536})
    checkpoint.preset = checkpoint.config["preset"] = "wide"
    checkpoint.extra["radar_file"] = wide
    path = save_checkpoint(checkpoint, tmp_path / "wide.pt")
    tracemalloc.start()
    try:
        with pytest.raises((LimitError, ProfileError), match="angle_bins = 65536"):
            load_checkpoint(path).build()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MiB allocated before refusing"


def test_a_checkpoint_whose_config_builds_a_larger_network_than_its_weights_is_refused(tiny_checkpoints):
    from models.checkpoint import CheckpointError, load_checkpoint

    checkpoint = load_checkpoint(tiny_checkpoints[0])
    checkpoint.build()  # as saved: builds
    checkpoint.config["doppler_channels"] = 10**6
    tracemalloc.start()
    try:
        with pytest.raises(CheckpointError, match="refused before allocating it"):
            checkpoint.build()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"{peak / 2**20:.0f} MiB allocated before refusing"
