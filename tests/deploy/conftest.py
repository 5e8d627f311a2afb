"""Fixtures of the deploy tests: the compose topology as processes on loopback.

``cluster`` is a real two-node Ray cluster: ``ray start --head`` and one ``ray start --address`` worker
joined to it, each in its own session (process group), so that each is stopped by its process group
id and nothing else on the machine is touched (never ``ray stop``: it kills every Ray of the user).
API processes are started and stopped by pid. The PostgreSQL ledger gets a table prefix of its own,
dropped afterwards.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import urllib.request
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import wait_until
from tests.pipelines.conftest import (  # noqa: F401
    BIN,
    REPO,
    free_port,
    node_ports,
    ray_env,
    ray_job_submit,
    small_store,
    stop_group,
)
from tests.service.conftest import ApiProcess, pg_prefix, postgres_url  # noqa: F401  (fixtures)


@dataclass
class LocalCluster:
    """A Ray head and one worker node on loopback."""

    gcs_address: str  # 127.0.0.1:PORT, for `ray start --address` and drivers' --address
    dashboard_url: str  # http://127.0.0.1:PORT, the jobs API (`ray job submit --address`)
    head_pgid: int
    worker_pgid: int
    temp_dir: Path

    def alive_nodes(self) -> list[dict]:
        with urllib.request.urlopen(f"{self.dashboard_url}/api/v0/nodes?limit=100", timeout=5) as resp:
            result = json.load(resp)["data"]["result"]["result"]
        return [n for n in result if n["state"] == "ALIVE"]


def _ray_start(args: list[str], log_name: str, temp_dir: Path) -> tuple[int, str]:
    """``ray start ARGS`` in a new session; returns its process group id and output (raises on failure)."""
    # Both "nodes" share one machine, so Serve's preference for replicas on the proxy's node means nothing
    # here; without it the router balances requests over every replica by queue length.
    env = ray_env(RAY_SERVE_PROXY_PREFER_LOCAL_NODE_ROUTING="0")
    proc = subprocess.Popen([str(BIN / "ray"), "start", *args], env=env, cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        stop_group(proc.pid, grace_s=3.0)
        raise
    if proc.returncode != 0:
        stop_group(proc.pid, grace_s=3.0)
        raise RuntimeError(f"ray start ({log_name}) failed ({proc.returncode}):\n{out[-3000:]}")
    return proc.pid, out


@pytest.fixture(scope="package")
def cluster() -> Iterator[LocalCluster]:
    """Ray head (1 CPU, dashboard and jobs API) + one worker node (1 CPU) joined to it, on 127.0.0.1."""
    temp_dir = Path(f"/tmp/rsg-deploy-{os.getpid()}")  # short: Ray's unix socket paths must fit 107 bytes
    gcs_port, dashboard_port = free_port(), free_port()
    common = ["--node-ip-address", "127.0.0.1", "--num-cpus", "1", "--object-store-memory", "150000000",
              "--temp-dir", str(temp_dir), "--disable-usage-stats"]
    head_pgid = worker_pgid = None
    try:
        head_pgid, _ = _ray_start(["--head", f"--port={gcs_port}", "--dashboard-host", "127.0.0.1",
                                   f"--dashboard-port={dashboard_port}", "--include-dashboard=true",
                                   f"--ray-client-server-port={free_port()}", *common, *node_ports()],
                                  "head", temp_dir)
        worker_pgid, _ = _ray_start([f"--address=127.0.0.1:{gcs_port}", *common, *node_ports()], "worker", temp_dir)
        cluster = LocalCluster(f"127.0.0.1:{gcs_port}", f"http://127.0.0.1:{dashboard_port}", head_pgid, worker_pgid,
                               temp_dir)
        # the jobs API comes up a little after `ray start` returns; then both nodes must be alive
        wait_until(lambda: len(cluster.alive_nodes()) == 2, timeout_s=90, errors=(OSError, KeyError, ValueError),
                   what="the two-node Ray cluster did not come up")
        yield cluster
    finally:
        left = []
        for pgid in (worker_pgid, head_pgid):
            if pgid is not None:
                left += stop_group(pgid, grace_s=5.0)
        shutil.rmtree(temp_dir, ignore_errors=True)
        assert not left, f"Ray processes left after stopping the cluster: {left}"


def submit_job(cluster: LocalCluster, *job: str, timeout_s: float = 240) -> dict:
    """``ray job submit --working-dir . -- python -m JOB...`` to the head; returns the JSON line the job printed."""
    log = ray_job_submit(cluster.dashboard_url, *job, timeout_s=timeout_s)
    return json.loads(next(line for line in reversed(log.splitlines()) if line.startswith('{"store"')))


@pytest.fixture
def api_processes(tmp_path) -> Iterator:
    """``start(command, port, env)`` -> ApiProcess; every one is stopped after the test."""
    started: list[ApiProcess] = []

    def start(command: list[str], port: int, env: dict[str, str]) -> ApiProcess:
        api = ApiProcess(command, port, env, tmp_path / f"api-{len(started)}-{uuid.uuid4().hex[:6]}.log")
        started.append(api)
        return api

    yield start
    for api in started:
        api.stop()
    assert all(api.proc.poll() is not None for api in started)


def uvicorn_command(port: int) -> list[str]:
    """The API as the compose file's alternative runs it: uvicorn with the app factory by import string."""
    return [sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", "127.0.0.1",
            "--port", str(port), "--log-level", "warning"]


def radarseg_serve_command(port: int) -> list[str]:
    """The API as the image's default command runs it (``radarseg serve``)."""
    return [sys.executable, "-m", "pipelines.cli", "serve", "--host", "127.0.0.1", "--port", str(port),
            "--log-level", "warning"]
