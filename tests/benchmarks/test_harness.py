"""The benchmark runner: every benchmark module is registered by name, and a run appends one record of what it
wrote, with the machine, the commit and the load, to the benchmark's history instead of replacing earlier ones."""

from __future__ import annotations

import json
import sys

import pytest

from benchmarks import harness


def test_every_benchmark_module_is_registered_once():
    names = [benchmark.name for benchmark in harness.REGISTRY]
    assert len(names) == len(set(names))
    assert sorted(names) == harness.benchmark_modules()


def test_a_run_appends_its_results_with_the_machine_and_commit(tmp_path):
    results, history = tmp_path / "results", tmp_path / "history"
    results.mkdir()
    (results / "other.json").write_text("{}")  # not written by the run: not in its record
    target = str(results / "fake.json")
    write = f"import json, sys; open({target!r}, 'w').write(json.dumps({{'ms': float(sys.argv[1])}}))"
    for ms in ("1.5", "2.5"):
        assert harness.recorded("fake", [sys.executable, "-c", write, ms], [ms], results=results, history=history) == 0
    records = [json.loads(line) for line in (history / "fake.jsonl").read_text().splitlines()]
    assert [r["results"] for r in records] == [{"fake.json": {"ms": 1.5}}, {"fake.json": {"ms": 2.5}}]
    first = records[0]
    assert first["argv"] == ["1.5"] and first["machine"]["cores"] >= 1 and first["machine"]["cpu"]
    assert len(first["commit"]) == 40 and isinstance(first["dirty"], bool) and len(first["load_average_before"]) == 3


def test_a_failed_run_records_nothing(tmp_path):
    code = harness.recorded("fake", [sys.executable, "-c", "raise SystemExit(3)"], [], results=tmp_path,
                            history=tmp_path / "history")
    assert code == 3 and not (tmp_path / "history").exists()


def test_a_benchmark_command_line_of_integer_options_writes_and_prints_its_figures(tmp_path, capsys):
    out = tmp_path / "results" / "fake.json"

    def run(frames: int, json_requests: int) -> dict:
        return {"frames": frames, "json_requests": json_requests}

    assert harness.int_options_main(out, run, "Fake.\n\nMore.", ["--json-requests", "7"], frames=3,
                                    json_requests=1) == 0
    assert json.loads(out.read_text()) == {"frames": 3, "json_requests": 7}
    assert json.loads(capsys.readouterr().out) == {"frames": 3, "json_requests": 7}


def test_integer_options_are_checked_and_the_figures_go_to_out_and_to_the_report(tmp_path, capsys):
    reported = []

    def run(frames: int, seed: int) -> dict:
        return {"frames": frames, "seed": seed}

    out = tmp_path / "elsewhere" / "figures.json"
    assert harness.int_options_main(tmp_path / "default.json", run, "Fake.", ["--out", str(out), "--seed", "-4"],
                                    report=reported.append, positive=("frames",), frames=2, seed=0) == 0
    assert json.loads(out.read_text()) == {"frames": 2, "seed": -4} == reported[0]
    assert not (tmp_path / "default.json").exists() and capsys.readouterr().out == ""
    with pytest.raises(SystemExit) as stopped:
        harness.int_options_main(tmp_path / "default.json", run, "Fake.", ["--frames", "0"], positive=("frames",),
                                 frames=2, seed=0)
    assert stopped.value.code == 2 and "--frames must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "default.json").exists()


def test_a_table_aligns_titles_with_their_values():
    table = harness.Table((("preset", "8"), ("s/frame", "8.3f"), ("share", "6.1%"), ("target", ">7")))
    assert table.header() == "preset    s/frame  share  target"
    assert table.row("small", 0.12345, 0.5, "-") == "small       0.123  50.0%       -"
    assert harness.Table((("stage", "<10"), ("ms", "6.1f")), separator="").row("grow", 2.25) == "grow         2.2"
    with pytest.raises(ValueError, match="a row of 2 values expected, got 1"):
        harness.Table((("stage", "<10"), ("ms", "6.1f"))).row("grow")
