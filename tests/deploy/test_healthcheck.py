"""deploy/healthcheck.py's process table (read from a /proc of files written here): the raylet check and the
process groups the pipeline tests wait on read the same ``/proc/PID/stat`` fields."""

from __future__ import annotations

from pathlib import Path

from deploy.healthcheck import process_stats, raylet_running


def _proc(tmp_path: Path, stats: dict[str, str]) -> Path:
    tmp_path.mkdir(exist_ok=True)
    for pid, stat in stats.items():
        (tmp_path / pid).mkdir()
        (tmp_path / pid / "stat").write_text(stat)
    (tmp_path / "self").mkdir()  # not a pid: passed over
    (tmp_path / "77").mkdir()  # a process that ended before its stat was read: passed over
    return tmp_path


def test_the_process_table_gives_each_name_with_its_state_parent_and_group(tmp_path):
    proc = _proc(tmp_path, {"12": "12 (ray::Worker (a)) S 1 40 40 0", "13": "13 (raylet) Z 1 40 40 0"})
    assert sorted(process_stats(proc)) == [(12, "ray::Worker (a)", ["S", "1", "40", "40", "0"]),
                                           (13, "raylet", ["Z", "1", "40", "40", "0"])]


def test_a_raylet_runs_only_when_one_is_not_a_zombie(tmp_path):
    assert not raylet_running(_proc(tmp_path / "a", {"13": "13 (raylet) Z 1 40 40 0"}))
    assert raylet_running(_proc(tmp_path / "b", {"13": "13 (raylet) Z 1 40 40 0", "14": "14 (raylet) S 1 4 4 0"}))
    assert not raylet_running(_proc(tmp_path / "c", {"15": "15 (raylet-x) S 1 4 4 0"}))
