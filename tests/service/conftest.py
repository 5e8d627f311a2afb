"""Fixtures of the service tests: tiny random-weight checkpoints of the ``small`` preset, a simulated
cube as .npy bytes, apps under the test client, a PostgreSQL ledger per test (own table prefix, dropped
afterwards), and real uvicorn processes on loopback (started here, stopped by pid)."""

from __future__ import annotations

import io
import os
import subprocess
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest

from deploy.healthcheck import process_stats
from pipelines.demo.serve_process import free_port, serve_command, stop_process
from radar.simulate import simulate_sequence
from service.settings import ModelSpec, Settings

REPO = Path(__file__).resolve().parents[2]
CLASSES = ("background", "pedestrian", "cyclist", "car")
NPY = {"content-type": "application/x-npy"}
KEYS = {"key-acme-0123456789abcdef": "acme", "key-globex-0123456789abcd": "globex",
        "key-admin-0123456789abcdef": "ops"}


def npy_bytes(array: np.ndarray, *, allow_pickle: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=allow_pickle)
    return buf.getvalue()


@pytest.fixture(scope="session")
def frame():
    """One simulated frame of the small preset."""
    return next(simulate_sequence("small", 1, seed=2))


@pytest.fixture(scope="session")
def cube_body(frame) -> bytes:
    return npy_bytes(frame.cube)


@pytest.fixture
def make_settings(tiny_checkpoints, tmp_path):
    """Settings serving the tiny model as ``tiny`` (untrained: threshold 0, one object), SQLite under tmp_path."""
    det, seg = tiny_checkpoints

    def build(**overrides) -> Settings:
        values = {"models": [ModelSpec(name="tiny", detector=det, segmenter=seg, score_threshold=0.0, max_objects=1)],
                  "data_dir": tmp_path / "data", "max_queue": 16}
        values.update(overrides)
        return Settings(**values)

    return build


@pytest.fixture
def client_for():
    """``client_for(settings)``: a started app under the test client; every one is closed after the test."""
    from fastapi.testclient import TestClient

    from service.main import create_app

    clients = []

    def start(settings: Settings) -> TestClient:
        client = TestClient(create_app(settings))
        client.__enter__()
        clients.append(client)
        return client

    yield start
    for client in clients:
        client.__exit__(None, None, None)


@pytest.fixture
def postgres_url() -> str:
    url = os.environ.get("RADARSEG_TEST_POSTGRES_URL")
    if not url:
        pytest.skip("RADARSEG_TEST_POSTGRES_URL is not set (CI sets it)")
    return url


@pytest.fixture
def pg_prefix(postgres_url) -> Iterator[str]:
    """A table prefix of this test's own; its ledger tables are dropped afterwards."""
    from service.accounting.ledger import Ledger

    prefix = f"t{uuid.uuid4().hex[:10]}_"
    yield prefix
    ledger = Ledger(postgres_url, table_prefix=prefix, pool_size=0)
    ledger.drop()
    ledger.dispose()


class StartWatch:
    """When to give up on a server that is starting. A loaded machine stretches a start-up's wall time without
    bound (more than 270 s seen for one that takes 10 s on a quiet machine), not the work it does; so the deadline is
    what the server itself used: ``cpu_s`` seconds of CPU time (its process tree's: a first build of the sparse
    engine runs the compiler in children), or ``stall_s`` seconds of wall time in which it used none (hung)."""

    def __init__(self, pid: int, *, cpu_s: float, stall_s: float = 120.0) -> None:
        self.pid, self.cpu_s, self.stall_s = pid, cpu_s, stall_s
        self.cpu = self.cpu_seconds()
        self.progressed = time.monotonic()

    def cpu_seconds(self) -> float:
        """CPU seconds (user and system) of the process, its children and their waited-for children."""
        stats = {pid: fields for pid, _, fields in process_stats()}
        children: dict[int, list[int]] = {}
        for pid, fields in stats.items():
            children.setdefault(int(fields[1]), []).append(pid)
        ticks, tree = 0, [self.pid]
        while tree:
            pid = tree.pop()
            if pid in stats:  # /proc/PID/stat after the name: utime, stime, cutime, cstime at 11..14
                ticks += sum(int(v) for v in stats[pid][11:15])
                tree.extend(children.get(pid, []))
        return ticks / os.sysconf("SC_CLK_TCK")

    def gave_up(self) -> str | None:
        """Why to stop waiting, or None while the server may still come up."""
        cpu, now = self.cpu_seconds(), time.monotonic()
        if cpu > self.cpu:
            self.cpu, self.progressed = cpu, now
        if cpu > self.cpu_s:
            return f"was not ready after {cpu:.0f} s of its CPU time (the limit: {self.cpu_s:.0f} s)"
        if now - self.progressed > self.stall_s:
            return f"used no CPU for {self.stall_s:.0f} s and was not ready (hung)"
        return None


class ApiProcess:
    """An API process on loopback (any command that serves ``service.main:create_app``), stopped by pid."""

    def __init__(self, command: list[str], port: int, env: dict[str, str], log_path: Path) -> None:
        self.port = port
        self.url = f"http://127.0.0.1:{port}"
        self.log_path = log_path
        self._log = log_path.open("w")
        self.proc = subprocess.Popen(command, cwd=REPO, stdout=self._log, stderr=subprocess.STDOUT,
                                     env={**os.environ, **env, "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})

    def wait_ready(self, timeout_s: float = 150.0) -> None:
        """Poll ``/readyz`` until it answers 200; RuntimeError with the log's tail when the process exits first or
        :class:`StartWatch` gives up on it (``timeout_s``: seconds of the server's own CPU time)."""
        watch = StartWatch(self.proc.pid, cpu_s=timeout_s)
        while self.proc.poll() is None:
            try:
                if httpx.get(f"{self.url}/readyz", timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            if reason := watch.gave_up():
                raise RuntimeError(f"the service {reason}:\n{self.log_path.read_text()[-3000:]}")
            time.sleep(0.3)
        raise RuntimeError(f"the service exited with {self.proc.returncode}:\n{self.log_path.read_text()[-3000:]}")

    def stop(self) -> None:
        """SIGTERM by pid (uvicorn shuts down gracefully), SIGKILL if it lingers."""
        stop_process(self.proc)
        self._log.close()


def Server(env: dict[str, str], log_path: Path) -> ApiProcess:  # noqa: N802 (reads like the class it builds)
    """A ``radarseg serve`` process on a free loopback port."""
    port = free_port()
    return ApiProcess(serve_command(port), port, env, log_path)


def GuardedServer(env: dict[str, str], log_path: Path, port: int | None = None,  # noqa: N802
                  log_level: str = "warning") -> ApiProcess:
    """A ``python -m service`` process on loopback (a free port unless given): the app under uvicorn with
    the settings' HTTP limits (head size and count, port bound before the models load)."""
    from service.server.http_server import server_command

    port = port or free_port()
    return ApiProcess(server_command(port, log_level), port, env, log_path)


@pytest.fixture
def serve(tmp_path):
    """``with serve(env) as server``: start ``radarseg serve`` with RADARSEG_* ``env``; stopped on exit."""

    @contextmanager
    def run(*envs: dict[str, str]) -> Iterator[list[ApiProcess]]:
        servers = [Server(env, tmp_path / f"server-{i}-{uuid.uuid4().hex[:6]}.log") for i, env in enumerate(envs)]
        try:
            for server in servers:  # started together: their start-ups overlap
                server.wait_ready()
            yield servers
        finally:
            for server in servers:
                server.stop()
            assert all(s.proc.poll() is not None for s in servers)

    return run


def server_env(tiny_checkpoints, **extra: str) -> dict[str, str]:
    """Environment serving the tiny model as ``tiny``."""
    import json

    det, seg = tiny_checkpoints
    models = [{"name": "tiny", "detector": str(det), "segmenter": str(seg), "score_threshold": 0.0, "max_objects": 1}]
    return {"RADARSEG_MODELS": json.dumps(models), "RADARSEG_MAX_QUEUE": "16", **extra}
