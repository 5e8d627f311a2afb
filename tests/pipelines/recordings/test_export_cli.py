"""``radarseg export recording``'s refusals: one line naming what was expected, exit code 2, nothing written."""

from __future__ import annotations

import pytest

from pipelines.cli import main


@pytest.mark.parametrize("arguments, expected", [
    (["--mcap", "{tmp}/a.mcap"], "not a zarr store"),
    ([], "name at least one output"),
])
def test_a_missing_store_or_no_output_is_one_line(tmp_path, capsys, arguments, expected):
    code = main(["export", "recording", str(tmp_path / "missing.zarr"),
                 *(a.format(tmp=tmp_path) for a in arguments)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and expected in err[0], err
    assert not (tmp_path / "a.mcap").exists()


def test_existing_outputs_and_bad_limits_are_refused(exported, tmp_path, capsys):
    store = str(exported["store"])
    assert main(["export", "recording", store, "--mcap", str(exported["mcap"])]) == 2
    assert "exists (pass --overwrite" in capsys.readouterr().err
    assert main(["export", "recording", store, "--rrd", str(tmp_path / "x.rrd"), "--limit", "0"]) == 2
    assert "--limit must be >= 1" in capsys.readouterr().err
    assert main(["export", "recording", store, "--rrd", str(tmp_path / "x.rrd"), "--sequence", "nope"]) == 2
    assert "--sequence 'nope'" in capsys.readouterr().err
    assert main(["export", "recording", store, "--mcap", str(tmp_path / "same"), "--rrd", str(tmp_path / "same")]) == 2
    assert "its own file" in capsys.readouterr().err
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / "same").exists()


def test_one_sequence_limited(exported, tmp_path, capsys):
    out = tmp_path / "one.mcap"
    assert main(["export", "recording", str(exported["store"]), "--mcap", str(out), "--limit", "2",
                 "--no-log-power"]) == 0
    assert "mcap, 2 frames" in capsys.readouterr().out
