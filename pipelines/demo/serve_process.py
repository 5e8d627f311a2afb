"""A ``radarseg serve`` process on loopback, as the demo, the benchmarks and the tests start it: a free port,
the command, waiting for ``/readyz``, and stopping it by its process id (SIGTERM, then SIGKILL)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def serve_command(port: int, log_level: str = "warning") -> list[str]:
    """``radarseg serve`` on ``port`` with this interpreter."""
    return [sys.executable, "-m", "pipelines.cli", "serve", "--port", str(port), "--log-level", log_level]


def wait_ready(url: str, proc: subprocess.Popen, log_path: Path, *, timeout_s: float, poll_s: float = 0.5) -> None:
    """Poll ``url/readyz`` until it answers 200; RuntimeError with the log's tail if the process exits first
    or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the service exited with {proc.returncode}:\n{Path(log_path).read_text()[-3000:]}")
        try:
            if httpx.get(f"{url}/readyz", timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(poll_s)
    raise RuntimeError(f"the service was not ready within {timeout_s} s:\n{Path(log_path).read_text()[-3000:]}")


def stop_process(proc: subprocess.Popen, *, grace_s: float = 20.0) -> None:
    """SIGTERM by pid (uvicorn shuts down gracefully), SIGKILL if it lingers past ``grace_s``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


@contextmanager
def serving(data_dir: Path, *, timeout_s: float, command: Callable[[int], list[str]] = serve_command,
            env: dict[str, str] | None = None) -> Iterator[tuple[str, int]]:
    """A service process on a free loopback port, ready: ``(url, port)``; stopped on leaving. It keeps its data
    under ``data_dir`` (its log: ``data_dir/server.log``), runs one OpenMP thread, and gets ``env`` on top of
    this process's environment; ``command(port)``: the command line (default ``radarseg serve``)."""
    port = free_port()
    log = data_dir / "server.log"
    child_env = {**os.environ, "RADARSEG_DATA_DIR": str(data_dir), "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1",
                 **(env or {})}
    with log.open("w") as out:
        proc = subprocess.Popen(command(port), stdout=out, stderr=subprocess.STDOUT, env=child_env)
    url = f"http://127.0.0.1:{port}"
    try:
        wait_ready(url, proc, log, timeout_s=timeout_s, poll_s=0.3)
        yield url, port
    finally:
        stop_process(proc)
