"""Shared fixtures of the pipeline tests: a real local Ray head on loopback, and process clean-up.

Ray processes are stopped by process group, never by ``ray stop``: ``ray stop`` kills every Ray
process of the machine's user, including the clusters of other jobs running beside the tests.
Each Ray we start runs in its own session (``start_new_session``), so its daemons, workers and job
drivers share one process group that we signal, then check empty.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from deploy.healthcheck import process_stats
from tests.conftest import save_tiny_checkpoints, wait_until  # noqa: F401 (re-exported for the pipelines tests)

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


def ray_env(**extra: str) -> dict[str, str]:
    """Environment for Ray subprocesses: the venv first on PATH (so a job's ``python`` is the venv's),
    token auth and usage stats off, no inherited cluster address."""
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    env.update(PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}", RAY_AUTH_MODE="disabled",
               RAY_USAGE_STATS_ENABLED="0", PYTHONUNBUFFERED="1")
    env.update(extra)
    return env


def free_port(preferred: int | None = None) -> int:
    for port in ([preferred] if preferred else []) + [0]:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return s.getsockname()[1]
    raise RuntimeError("no free port")


def node_ports() -> list[str]:
    """``ray start`` options for the per-node ports that default to fixed numbers (the dashboard agent's among them):
    free ones, so that two nodes on one machine, a ``ray.init`` cluster of another test, or other engineers' Rays
    never take them first. A head whose agent lost its port never serves ``ray job submit`` ("No available
    agent"), however long a submission retries."""
    return [f"--dashboard-agent-listen-port={free_port()}", f"--metrics-export-port={free_port()}",
            f"--runtime-env-agent-port={free_port()}"]


def group_alive(pgid: int) -> list[int]:
    """Pids (not zombies) whose process group is ``pgid``."""
    return [pid for pid, _, fields in process_stats() if fields[0] != "Z" and int(fields[2]) == pgid]


def stop_group(pgid: int, *, grace_s: float = 10.0) -> list[int]:
    """SIGTERM the group, wait, SIGKILL what is left; returns the pids still alive afterwards."""
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return []
        deadline = time.monotonic() + wait
        while group_alive(pgid) and time.monotonic() < deadline:
            time.sleep(0.2)
        if not group_alive(pgid):
            return []
    return group_alive(pgid)


# Refusals of a loaded machine's Ray that a later submission gets past: the dashboard answers before its job agent
# is up, and the agent times out fetching the working-directory package it was just sent (its message says to
# submit again).
TRANSIENT_SUBMIT_ERRORS = ("No available agent", "Failed to download runtime_env file package")


def ray_job_submit(dashboard_url: str, *job: str, timeout_s: float = 240) -> str:
    """``ray job submit --working-dir . -- python -m JOB...``; returns the job's log. The dashboard answers
    before its job agent is up on a loaded machine ("No available agent"): such a refusal, and the other
    :data:`TRANSIENT_SUBMIT_ERRORS`, are retried."""
    cmd = [str(BIN / "ray"), "job", "submit", "--address", dashboard_url, "--working-dir", ".", "--",
           "python", "-m", *job]
    deadline = time.monotonic() + 300  # a 2-core machine has taken more than 180 s to start the agent (CI, 2026-12-03)
    while True:
        proc = subprocess.run(cmd, cwd=REPO, env=ray_env(), capture_output=True, text=True, timeout=timeout_s)
        log = proc.stdout + proc.stderr
        if proc.returncode == 0 or not any(t in log for t in TRANSIENT_SUBMIT_ERRORS) \
                or time.monotonic() > deadline:
            break
        time.sleep(3)
    assert proc.returncode == 0 and "succeeded" in log, log[-4000:]
    return log


class RayHead:
    def __init__(self, dashboard_url: str, pgid: int, temp_dir: Path):
        self.dashboard_url = dashboard_url
        self.pgid = pgid
        self.temp_dir = temp_dir


@pytest.fixture(scope="session")
def ray_head(tmp_path_factory):
    """``ray start --head`` on loopback with the dashboard (for ``ray job submit``); stopped at the end."""
    temp_dir = Path(f"/tmp/rsg-ray-{os.getpid()}")  # short: Ray's unix socket paths must fit 107 bytes
    dashboard_port = free_port(8265)
    cmd = [str(BIN / "ray"), "start", "--head", f"--port={free_port()}", "--node-ip-address", "127.0.0.1",
           "--dashboard-host", "127.0.0.1", f"--dashboard-port={dashboard_port}", "--include-dashboard=true",
           f"--ray-client-server-port={free_port()}", "--num-cpus", "2", "--object-store-memory", "200000000",
           "--temp-dir", str(temp_dir), "--disable-usage-stats", *node_ports()]
    proc = subprocess.Popen(cmd, env=ray_env(), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    pgid = proc.pid
    head = RayHead(f"http://127.0.0.1:{dashboard_port}", pgid, temp_dir)
    try:
        out, _ = proc.communicate(timeout=120)
        if proc.returncode != 0:
            raise RuntimeError(f"ray start failed ({proc.returncode}):\n{out[-3000:]}")
        def dashboard_up() -> bool:
            with urllib.request.urlopen(f"{head.dashboard_url}/api/version", timeout=2) as resp:
                return resp.status == 200

        # the jobs API comes up a little after `ray start` returns
        wait_until(dashboard_up, timeout_s=60, what="the Ray dashboard did not come up")
        yield head
    finally:
        left = stop_group(pgid, grace_s=3.0)
        shutil.rmtree(temp_dir, ignore_errors=True)
        assert not left, f"Ray processes left after stopping the head: {left}"


def build_store_inline(cfg):
    """The job run in-process (no Ray: shards in this process, in order): fast stores for tests of the
    store and the Dataset. The Ray paths are tested in test_preprocess.py."""
    from dataclasses import replace

    from pipelines.datasets.preprocess import main

    return Path(main(replace(cfg, in_process=True))["store"])




def sim_store(tmp_path_factory, name: str, **fields):
    """A store of simulated ``small`` frames built without Ray (the runner's in-process mode)."""
    from pipelines.datasets.preprocess import PreprocessConfig

    out = tmp_path_factory.mktemp(name) / f"{name}.zarr"
    return build_store_inline(PreprocessConfig(source="sim", out=str(out), preset="small", progress=False, **fields))


@pytest.fixture(scope="session")
def small_store(tmp_path_factory):
    """2 sequences x 3 frames, seed 5, shards of 2 frames; no test split."""
    return sim_store(tmp_path_factory, "small", sequences=2, frames=3, seed=5, split_fractions=(0.5, 0.5, 0.0),
                     shard_frames=2)


def assert_store_matches_simulator(path, *, preset: str, sequences: int, frames: int, seed: int) -> None:
    """Every array of a ``sim`` store equals what the simulator's own frames, labels and object table give."""
    import numpy as np
    import zarr

    from models.detector.targets import render_heatmap
    from pipelines.datasets.store import OBJECT_FIELDS, open_store
    from radar import transforms
    from radar.simulate import simulate_sequence

    root = open_store(path)
    assert root.attrs["preset"] == preset
    assert root["input"].shape[0] == sequences * frames
    assert isinstance(root["input"].metadata.codecs[0], zarr.codecs.ShardingCodec)
    col = {name: i for i, name in enumerate(OBJECT_FIELDS)}
    slot = 0
    for s in range(sequences):
        for frame in simulate_sequence(preset, frames, seed=seed, sequence_index=s):
            assert root["valid"][slot] == 1
            assert root["sequence_id"][slot] == s and root.attrs["sequences"][s] == frame.sequence
            assert root["frame_index"][slot] == frame.index
            # Ray workers run BLAS single-threaded (OMP_NUM_THREADS=1), so the cube may differ from this
            # process's in the last float32 bits: allow float16 rounding and 0.01 dB.
            np.testing.assert_allclose(root["input"][slot].astype(np.float32), transforms.log_power(frame.cube),
                                       rtol=2**-10, atol=0.01)
            np.testing.assert_array_equal(root["labels"][slot], frame.labels)
            np.testing.assert_array_equal(root["instances"][slot], frame.instances)
            np.testing.assert_array_equal(root["ra_mask"][slot], frame.ra_mask())
            np.testing.assert_array_equal(root["rd_mask"][slot], frame.rd_mask())
            targets = [o for o in frame.objects if o.n_voxels > 0]
            table = root["objects"][slot]
            assert root["n_objects"][slot] == len(targets)
            assert np.isnan(table[len(targets):]).all()
            for row, o in zip(table, targets, strict=False):
                assert row[col["instance_id"]] == o.instance_id and row[col["class_id"]] == o.class_id
                np.testing.assert_allclose(row[[col["range_bin"], col["angle_bin"], col["doppler_bin"],
                                                col["x"], col["y"]]],
                                           [o.centre_range_bin, o.centre_angle_bin, o.doppler_bin,
                                            o.centre_x, o.centre_y], rtol=1e-6, atol=1e-5)
                cells = np.array([o.centre_range_bin, o.centre_angle_bin]) / 4
                np.testing.assert_allclose(row[[col["offset_range"], col["offset_angle"]]],
                                           cells - np.floor(cells), atol=1e-5)
                assert row[col["n_voxels"]] == o.n_voxels
                assert row[col["track_id"]] == o.track_id >= 1  # tracking truth: identity and velocity
                np.testing.assert_allclose(row[[col["vx"], col["vy"]]], [o.true_vx, o.true_vy], rtol=1e-6, atol=1e-6)
            centres = [[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in targets]
            expected = render_heatmap(np.array(centres).reshape(-1, 3), frame.cube.shape[:2])
            np.testing.assert_array_equal(root["heatmap"][slot], expected.astype(np.float16))
            slot += 1


@pytest.fixture(scope="session")
def seq_store(tmp_path_factory):
    """3 sequences x 6 frames (one per split), seed 3."""
    return sim_store(tmp_path_factory, "seq", sequences=3, frames=6, seed=3, split_fractions=(0.34, 0.33, 0.33),
                     shard_frames=6)
