"""benchmarks/learning_curves.py reads a history detector's curve as scored with history or on single cubes."""

import json
import subprocess
import sys
from pathlib import Path

from benchmarks.learning_curves import read_curve

REPO = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path) -> Path:
    run = tmp_path / "det"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"stage": "detector"}))
    points = [{"epoch": 0, "step": 0, "cpu_s": 0.0, "val_mAP": 0.1, "val_mAP_single": 0.05},
              {"epoch": 1, "step": 10, "cpu_s": 60.0, "val_mAP": 0.5, "val_mAP_single": 0.4}]
    (run / "curve.jsonl").write_text("\n".join(json.dumps(p) for p in points) + "\n")
    return run


def test_single_reads_the_single_cube_figures(tmp_path):
    run = _run(tmp_path)
    assert [p["val_mAP"] for p in read_curve(run)["points"]] == [0.1, 0.5]
    single = read_curve(run, suffix="_single")["points"]
    assert [p["val_mAP"] for p in single] == [0.05, 0.4] and [p["cpu_s"] for p in single] == [0.0, 60.0]


def test_the_command_draws_both_and_refuses_another_reading(tmp_path):
    run = _run(tmp_path)
    out = tmp_path / "curves"
    command = [sys.executable, "-m", "benchmarks.learning_curves", "--stage", "detector"]
    done = subprocess.run([*command, f"hist={run}", f"hist-single={run}#single", "--out", str(out)], cwd=REPO,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    curves = json.loads(out.with_suffix(".json").read_text())["curves"]
    assert curves["hist-single"]["points"][-1]["val_mAP"] == 0.4 and out.with_suffix(".png").stat().st_size > 0
    refused = subprocess.run([*command, f"x={run}#double", "--out", str(out)], cwd=REPO, capture_output=True, text=True)
    assert refused.returncode == 2 and "#single" in refused.stderr
