"""The preprocessing job: arguments, a real ``ray job submit`` to a local head, the embedded-Ray run,
resume after a killed run, and quarantine of bad cubes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipelines.cli import main as cli_main
from pipelines.datasets.preprocess import PreprocessConfig, _split_by_fractions, main, plan_job, simulated_frames
from pipelines.datasets.sharded_store import done_shards
from pipelines.datasets.store import array_checksums, open_store, summarise
from pipelines.jobs import job_module, parse_config, run_module
from pipelines.ray_runtime import init_ray
from radar import transforms
from radar.errors import DataError
from radar.io.recording import Recording
from radar.simulate import SIMULATOR_VERSION, SimulatorConfig, simulate_sequence
from tests.pipelines.conftest import (
    REPO,
    assert_store_matches_simulator,
    build_store_inline,
    ray_env,
    ray_job_submit,
    stop_group,
)

SUBMIT_ARGS = ["--source", "sim", "--preset", "small", "--sequences", "3", "--frames", "8", "--seed", "11"]


def parse_args(argv: list[str]) -> PreprocessConfig:
    return parse_config(job_module("pipelines.datasets.preprocess"), argv,
                        prog="python -m pipelines.datasets.preprocess")


# --------------------------------------------------------------------------- no Ray
def test_wrong_arguments_fail_before_any_work(tmp_path, small_recording, capsys):
    import ray

    out = tmp_path / "s.zarr"
    bad = [
        (["--source", "simulator"], "--source must be"),
        (["--source", "recording:" + str(tmp_path / "missing")], "no such recording directory"),
        (["--source", f"recording:{small_recording}", "--preset", "small"], "only with --source sim"),
        (["--source", "sim", "--sequences", "0"], "must be >= 1"),
        (["--source", "sim", "--tasks", "0"], "--tasks must be >= 1"),
        (["--source", "sim", "--split-fractions", "0.5", "0.2", "0.2"], "summing to 1"),
        (["--source", "sim", "--split-fractions", "0", "0.5", "0.5"], "train > 0"),
        (["--source", "sim", "--preset", "tiny"], "unknown radar preset 'tiny'"),
    ]
    for args, message in bad:
        # python -m pipelines.datasets.preprocess
        assert run_module("pipelines.datasets.preprocess", [*args, "--out", str(out)]) == 2
        assert message in capsys.readouterr().err, args
    assert not out.exists()
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not a radarseg store"):
        main(PreprocessConfig(source="sim", out=str(tmp_path / "busy")))
    with pytest.raises(ValueError, match="train split empty"):
        main(PreprocessConfig(source="sim", out=str(out), sequences=1, split_fractions=(0.4, 0.6, 0.0)))
    assert not ray.is_initialized() and not out.exists()
    try:  # argparse's exit, or the command's one-line error: status 2 either way, and nothing written
        status = cli_main(["preprocess", "--source", "sim", "--frames", "-1", "--out", str(out)])
    except SystemExit as exc:
        status = exc.code
    assert status == 2 and not out.exists()


def test_split_by_sequence_fractions():
    names = [f"seq_{i:03d}" for i in range(10)]
    splits = _split_by_fractions(names, (0.6, 0.2, 0.2))
    assert [splits[n] for n in names] == ["train"] * 6 + ["val"] * 2 + ["test"] * 2
    assert set(_split_by_fractions(names[:1], (0.7, 0.15, 0.15)).values()) == {"train"}


def test_simulated_frames_start_mid_sequence_as_simulate_sequence():
    reference = list(simulate_sequence("small", 4, seed=3, sequence_index=1))
    frames = list(simulated_frames("small", 3, 1, [1, 3]))
    assert [f.index for f in frames] == [1, 3]
    for frame, ref in zip(frames, (reference[1], reference[3]), strict=True):
        np.testing.assert_array_equal(frame.cube, ref.cube)
        np.testing.assert_array_equal(frame.labels, ref.labels)
        assert frame.objects == ref.objects


def test_a_store_records_the_simulator_of_its_frames(small_recording, tmp_path):
    # a store of a simulated recording carries the recording's simulator; a resumed run must share it
    recorded = json.loads((small_recording / "recording.json").read_text())["simulator"]
    assert recorded["version"] == SIMULATOR_VERSION
    cfg = PreprocessConfig(source=f"recording:{small_recording}", out=str(tmp_path / "rec.zarr"), progress=False)
    assert plan_job(cfg).identity()["simulator"] == recorded
    store = build_store_inline(cfg)
    assert open_store(store).attrs["simulator"] == recorded
    # a simulated store: the default options of this version
    sim = PreprocessConfig(source="sim", out=str(tmp_path / "sim.zarr"), sequences=1, frames=1, progress=False)
    assert plan_job(sim).identity()["simulator"] == SimulatorConfig().stamp()


# --------------------------------------------------------------------------- Ray
@pytest.mark.ray
@pytest.mark.slow
def test_ray_job_submit_on_a_local_cluster(ray_head, tmp_path):
    out = tmp_path / "STORE.zarr"
    log = ray_job_submit(ray_head.dashboard_url, "pipelines.datasets.preprocess", *SUBMIT_ARGS, "--out", str(out),
                         "--no-progress", "--json")
    result = json.loads(next(line for line in log.splitlines() if line.startswith('{"store"')))
    assert result["written"] == 24 and result["quarantined"] == 0 and result["shards_run"] == 3
    assert_store_matches_simulator(out, preset="small", sequences=3, frames=8, seed=11)
    attrs = open_store(out).attrs.asdict()
    assert attrs["job"]["address"] is None and attrs["normalisation"]["frames"] == 8  # 3 sequences: 1/1/1


@pytest.fixture(scope="module")
def embedded_ray():
    """One embedded local Ray for the in-process runs of this module (main() reuses it)."""
    import ray

    init_ray(None, num_cpus=2, object_store_bytes=200_000_000)
    try:
        yield
    finally:
        ray.shutdown()


def _job(*args: str, env_extra: dict[str, str] | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipelines.datasets.preprocess", *args, "--no-progress", "--json"],
                            cwd=REPO,
                            env=ray_env(**(env_extra or {})), stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


@pytest.mark.ray
@pytest.mark.slow
def test_killed_run_resumes_to_an_identical_store(tmp_path, embedded_ray):
    args = ["--source", "sim", "--preset", "small", "--sequences", "2", "--frames", "10", "--seed", "4",
            "--shard-frames", "1", "--tasks", "1"]
    out = tmp_path / "resumed.zarr"
    # 1. an embedded-Ray run, killed (SIGKILL to its whole process group) once a few shards are done
    # No wall-clock deadline for the first shards: a loaded machine stretches Ray's start without bound (a run that
    # ends first, or writes nothing, fails the assertions below); how long it took sets the resumed run's deadline.
    started = time.monotonic()
    proc = _job(*args, "--out", str(out))
    while len(done_shards(out)) < 2 and proc.poll() is None:
        time.sleep(0.005)
    two_shards_s = time.monotonic() - started  # Ray's start and two shards
    os.killpg(proc.pid, signal.SIGKILL)  # the driver, its embedded Ray and the workers mid-write
    left = stop_group(proc.pid, grace_s=2.0)
    proc.wait(timeout=10)
    assert not left, f"processes left after killing the job: {left}"
    n_done = len(done_shards(out))
    assert 0 < n_done < 20, f"the kill should land mid-run ({n_done} of 20 shards done)"
    assert not open_store(out, require_complete=False).attrs["complete"]
    # 2. the same command again, embedded: skips the done shards and finishes
    proc = _job(*args, "--out", str(out))
    # Ray's start and at most 18 shards take under 9 times the first run's start and two shards: twice that
    output, _ = proc.communicate(timeout=max(180.0, 18 * two_shards_s))
    assert proc.returncode == 0, output[-3000:]
    result = json.loads(output.strip().splitlines()[-1])
    assert result["shards_skipped"] >= n_done and result["shards_skipped"] + result["shards_run"] == 20
    # 3. a straight run gives the same arrays, byte for byte
    straight = tmp_path / "straight.zarr"
    main(parse_args([*args, "--out", str(straight), "--no-progress"]))
    assert array_checksums(out) == array_checksums(straight)
    for key in ("normalisation", "class_voxel_counts", "report"):
        assert open_store(out).attrs[key] == open_store(straight).attrs[key]
    assert_store_matches_simulator(out, preset="small", sequences=2, frames=10, seed=4)
    # 4. a rerun of a complete store does no work; other arguments on it are refused
    again = main(parse_args([*args, "--out", str(out), "--no-progress"]))
    assert again["shards_run"] == 0 and array_checksums(out) == array_checksums(straight)
    with pytest.raises(ValueError, match="written with other arguments"):
        plan_job(PreprocessConfig(source="sim", out=str(out), preset="small", sequences=2, frames=10, seed=5,
                                  shard_frames=1))


def _corrupt(recording: Path, sequence: str, index: int, how: str) -> None:
    path = recording / sequence / "cubes" / f"{index:06d}.npy"
    if how == "nan":
        cube = np.load(path)
        cube[3, 4, 5] = np.nan
        np.save(path, cube)
    elif how == "shape":
        np.save(path, np.zeros((64, 128, 32), np.complex64))
    elif how == "dtype":
        np.save(path, np.zeros((128, 128, 32), np.int16))
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[:5000])


@pytest.mark.ray
@pytest.mark.slow
def test_bad_cubes_are_quarantined_and_the_job_carries_on(tmp_path, small_recording, embedded_ray, capsys):
    rec = tmp_path / "rec"
    shutil.copytree(small_recording, rec)  # 2 sequences x 3 frames
    bad = {("seq_000", 1): ("nan", "NaN or Inf"), ("seq_001", 0): ("shape", "shape"),
           ("seq_001", 1): ("dtype", "dtype"), ("seq_001", 2): ("truncated", "truncated")}
    for (seq, index), (how, _) in bad.items():
        _corrupt(rec, seq, index, how)
    out = tmp_path / "q.zarr"
    assert cli_main(["preprocess", "--source", f"recording:{rec}", "--out", str(out), "--shard-frames", "2",
                     "--split-fractions", "0.5", "0.5", "0", "--no-progress"]) == 0
    assert "2/6 frames written, 4 quarantined" in capsys.readouterr().out
    root = open_store(out)
    report = root.attrs["report"]
    assert [(q["sequence"], q["index"]) for q in report["quarantined"]] == sorted(bad)
    for q in report["quarantined"]:
        assert bad[(q["sequence"], q["index"])][1] in q["reason"] and q["sequence"] in q["reason"]
    np.testing.assert_array_equal(root["valid"][:], [1, 0, 1, 0, 0, 0])
    assert not root["input"][1].any() and np.isnan(root["objects"][1]).all()  # quarantined: nothing written
    reader = Recording(small_recording)
    for slot, (seq, index) in ((0, ("seq_000", 0)), (2, ("seq_000", 2))):
        frame = reader.read_frame(seq, index)
        np.testing.assert_array_equal(root["input"][slot], transforms.log_power(frame.cube).astype(np.float16))
        np.testing.assert_array_equal(root["labels"][slot], frame.labels)
    assert summarise(out)["frames"] == {"train": 2, "val": 0, "test": 0}
    assert cli_main(["store", "info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "quarantined: 4" in info and "seq_001/2 (slot 5)" in info

    # every input bad: a clear failure, no complete store
    all_bad = tmp_path / "allbad"
    shutil.copytree(small_recording, all_bad)
    for seq in ("seq_000", "seq_001"):
        for index in range(3):
            _corrupt(all_bad, seq, index, "nan")
    with pytest.raises(DataError, match="every one of the 6 input frames is bad"):
        main(PreprocessConfig(source=f"recording:{all_bad}", out=str(tmp_path / "bad.zarr"), progress=False))
    assert not open_store(tmp_path / "bad.zarr", require_complete=False).attrs["complete"]


@pytest.mark.ray
def test_adc_recordings_preprocess_like_cube_recordings(tmp_path, embedded_ray, capsys):
    from pipelines.datasets.record import simulate_recording

    adc_rec = simulate_recording(preset="small", sequences=2, frames=2, seed=5, out=tmp_path / "adc", progress=False,
                                 adc=True)
    cube_rec = simulate_recording(preset="small", sequences=2, frames=2, seed=5, out=tmp_path / "cube",
                                  progress=False)
    common = ["--split-fractions", "0.5", "0.5", "0", "--no-progress"]
    assert cli_main(["preprocess", "--source", f"adc-recording:{adc_rec}", "--out", str(tmp_path / "a.zarr"),
                     *common]) == 0
    assert cli_main(["preprocess", "--source", f"recording:{cube_rec}", "--out", str(tmp_path / "c.zarr"),
                     *common]) == 0
    a, c = open_store(tmp_path / "a.zarr"), open_store(tmp_path / "c.zarr")
    np.testing.assert_allclose(a["input"][:].astype(np.float32), c["input"][:].astype(np.float32), atol=0.07)
    np.testing.assert_array_equal(a["labels"][:], c["labels"][:])
    assert a.attrs["schema"]["content"] == "log_power_db" and a.attrs["schema"]["profile"] == "small"
    assert run_module("pipelines.datasets.preprocess", ["--source", f"adc-recording:{cube_rec}", "--out",
                                               str(tmp_path / "x.zarr"), *common]) == 2
    assert "holds RAD cubes, not ADC samples" in capsys.readouterr().err
