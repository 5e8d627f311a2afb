"""The benchmark runner: every benchmark module is registered by name, and a run appends one record of what it
wrote, with the machine, the commit and the load, to the benchmark's history instead of replacing earlier ones."""

from __future__ import annotations

import json
import sys

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
