"""The compose stack of deploy/docker-compose.yml on a real Docker engine, for tests/deploy/test_compose_stack.py.

:func:`engine_or_skip` finds the engine and a Compose (v2's ``docker compose`` or 1.29's ``docker-compose``);
:func:`build_images` builds the offline base images (deploy/offline/build-base-images.sh, kept when present),
takes the torch wheel pip finds on this machine into deploy/wheels and builds the project's image (Docker's layer
cache makes a rebuild after a code change cheap); :class:`Stack` runs compose commands on one project of its own
(its own bridge network and volumes, host ports picked free on 127.0.0.1) and reads its containers' state.
Every wait is bounded; traffic goes only to loopback and to the project's bridge network.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import pytest

from tests.pipelines.conftest import REPO, free_port

COMPOSE_FILE = REPO / "deploy" / "docker-compose.yml"
REQUIRE_ENV = "RADARSEG_REQUIRE_DOCKER"  # "1": a missing engine fails the lane instead of skipping it (CI)
IMAGE = os.environ.get("RADARSEG_TEST_IMAGE", "radarseg-test/radarseg:latest")
PYTHON_IMAGE = os.environ.get("RADARSEG_PYTHON_IMAGE", "radarseg-test/python:3.11")
POSTGRES_IMAGE = os.environ.get("RADARSEG_POSTGRES_IMAGE", "radarseg-test/postgres:15")
WHEELS = REPO / "deploy" / "wheels"
APP_UID = 10001


def free_pair(attempts: int = 50) -> int:
    """A port p with p and p + 1 both free on 127.0.0.1."""
    for _ in range(attempts):
        first = free_port()
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", first + 1))
            except OSError:
                continue
        return first
    raise RuntimeError(f"no two adjacent free ports in {attempts} tries")


def run(args: list[str], *, timeout_s: float, env: dict[str, str] | None = None,
        check: bool = True) -> subprocess.CompletedProcess:
    """A command with a time limit; with ``check`` a failure raises with the command's output tail."""
    proc = subprocess.run(args, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s)
    if check and proc.returncode != 0:
        raise AssertionError(f"{' '.join(args[:6])} ... failed ({proc.returncode}):\n"
                             f"{(proc.stdout + proc.stderr)[-4000:]}")
    return proc


def engine_or_skip() -> list[str]:
    """The Compose command (``docker compose`` or ``docker-compose``); skips (fails under REQUIRE_ENV) without one."""
    def missing(reason: str) -> None:
        if os.environ.get(REQUIRE_ENV) == "1":
            pytest.fail(f"{reason} ({REQUIRE_ENV}=1: the deploy lane must run here)")
        pytest.skip(f"{reason}: the compose stack needs a running Docker engine (.ci/run starts one)")

    if shutil.which("docker") is None:
        missing("no docker command")
    if run(["docker", "info", "--format", "{{.ServerVersion}}"], timeout_s=30, check=False).returncode != 0:
        missing("no Docker engine answers (docker info failed)")
    if run(["docker", "compose", "version"], timeout_s=30, check=False).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    missing("neither `docker compose` nor `docker-compose` is installed")
    raise AssertionError("unreachable")


def torch_wheel() -> None:
    """The torch wheel of the pinned version into deploy/wheels, as pip finds it (a local wheel folder here)."""
    version = next(line.split("==")[1].strip('",') for line in (REPO / "pyproject.toml").read_text().splitlines()
                   if line.strip().startswith('"torch=='))
    if not list(WHEELS.glob(f"torch-{version}*.whl")):
        run([sys.executable, "-m", "pip", "download", f"torch=={version}", "--no-deps", "-q", "-d", str(WHEELS)],
            timeout_s=600)


def build_images() -> dict[str, float]:
    """The offline base images and the project's image; returns the seconds each step took."""
    times = {}
    started = time.monotonic()
    run([str(REPO / "deploy" / "offline" / "build-base-images.sh")], timeout_s=900)
    times["base_images_s"] = time.monotonic() - started
    torch_wheel()
    started = time.monotonic()
    run(["docker", "build", "-q", "-f", "deploy/Dockerfile", "--build-arg", f"PYTHON_IMAGE={PYTHON_IMAGE}",
         "-t", IMAGE, "."], timeout_s=1500)
    times["image_build_s"] = time.monotonic() - started
    return times


@dataclass
class Stack:
    """One compose project of deploy/docker-compose.yml with the test's secrets, images and host ports."""

    compose: list[str]
    project: str = field(default_factory=lambda: f"radarseg-test-{os.getpid()}")
    keys: dict[str, str] = field(default_factory=lambda: {"key-acme-0123456789abcdef": "acme",
                                                          "key-beta-0123456789abcdef": "beta"})
    ports: dict[str, int] = field(default_factory=lambda: {name: free_port() for name in ("dashboard", "client",
                                                                                         "serve")})

    def __post_init__(self) -> None:
        first = free_pair()
        self.api_ports = f"{first}-{first + 1}"  # one host port per API replica
        self.env = {**os.environ, "COMPOSE_PROJECT_NAME": self.project, "RADARSEG_IMAGE": IMAGE,
                    "RADARSEG_PYTHON_IMAGE": PYTHON_IMAGE, "RADARSEG_POSTGRES_IMAGE": POSTGRES_IMAGE,
                    "RAY_AUTH_TOKEN": os.urandom(16).hex(), "POSTGRES_PASSWORD": os.urandom(8).hex(),
                    "RADARSEG_API_KEYS": json.dumps(self.keys), "RAY_WORKER_NUM_CPUS": "1",
                    "RAY_DASHBOARD_HOST_PORT": str(self.ports["dashboard"]),
                    "RAY_CLIENT_HOST_PORT": str(self.ports["client"]),
                    "RAY_SERVE_HOST_PORT": str(self.ports["serve"]), "RADARSEG_API_HOST_PORTS": self.api_ports,
                    "RADARSEG_TORCH_THREADS": "1"}

    @property
    def dashboard_url(self) -> str:
        return f"http://127.0.0.1:{self.ports['dashboard']}"

    def run(self, *args: str, timeout_s: float = 300, check: bool = True) -> subprocess.CompletedProcess:
        return run([*self.compose, "-f", str(COMPOSE_FILE), *args], timeout_s=timeout_s, env=self.env, check=check)

    def up(self) -> None:
        self.run("up", "-d", "--no-build", "--scale", "ray-worker=2", "--scale", "api=2", timeout_s=600)

    def containers(self, service: str | None = None) -> list[str]:
        """Ids of the project's containers (of one service), running or not, oldest first."""
        labels = ["--filter", f"label=com.docker.compose.project={self.project}"]
        if service:
            labels += ["--filter", f"label=com.docker.compose.service={service}"]
        ids = run(["docker", "ps", "-aq", *labels], timeout_s=30).stdout.split()
        return sorted(ids, key=lambda c: self.inspect(c)["Created"])

    def inspect(self, container: str) -> dict:
        return json.loads(run(["docker", "inspect", container], timeout_s=30).stdout)[0]

    def health(self) -> dict[str, str]:
        """Container name -> health status (or the state where it has none)."""
        out = {}
        for container in self.containers():
            state = self.inspect(container)["State"]
            out[self.inspect(container)["Name"].lstrip("/")] = state.get("Health", {}).get("Status", state["Status"])
        return out

    def wait_healthy(self, count: int, timeout_s: float = 300) -> float:
        """Seconds until ``count`` containers are all healthy; fails with their states after ``timeout_s``."""
        started = time.monotonic()
        while True:
            health = self.health()
            if len(health) == count and set(health.values()) == {"healthy"}:
                return time.monotonic() - started
            if time.monotonic() - started > timeout_s:
                raise AssertionError(f"not all healthy within {timeout_s:.0f} s: {health}\n{self.logs()[-6000:]}")
            time.sleep(2.0)

    def wait_ready(self, timeout_s: float = 300) -> list[str]:
        """The API replicas' URLs once each answers /readyz with 200 (models loaded, ledger up)."""
        started = time.monotonic()
        while True:
            urls = [f"http://127.0.0.1:{self.host_port(c)}" for c in self.containers("api")]
            answers = []
            for url in urls:
                try:
                    answers.append(httpx.get(f"{url}/readyz", timeout=10))
                except httpx.HTTPError as error:
                    answers.append(error)
            if all(isinstance(a, httpx.Response) and a.status_code == 200 for a in answers):
                return urls
            if time.monotonic() - started > timeout_s:
                raise AssertionError(f"API replicas not ready within {timeout_s:.0f} s: "
                                     f"{[getattr(a, 'text', a) for a in answers]}")
            time.sleep(2.0)

    def host_port(self, container: str, port: int = 8000) -> int:
        bindings = self.inspect(container)["NetworkSettings"]["Ports"][f"{port}/tcp"]
        return int(bindings[0]["HostPort"])

    def exec(self, container: str, *args: str, timeout_s: float = 120, check: bool = True,
             user: str | None = None) -> subprocess.CompletedProcess:
        return run(["docker", "exec", *(["-u", user] if user else []), container, *args], timeout_s=timeout_s,
                   check=check)

    def psql(self, sql: str) -> str:
        (postgres,) = self.containers("postgres")
        return self.exec(postgres, "psql", "-U", "radarseg", "-d", "radarseg", "-At", "-c", sql).stdout.strip()

    def volume_path(self, volume: str) -> Path:
        """Where a named volume of the project lies on this host (read as root)."""
        out = run(["docker", "volume", "inspect", f"{self.project}_{volume}"], timeout_s=30).stdout
        return Path(json.loads(out)[0]["Mountpoint"])

    def logs(self, tail: int = 40) -> str:
        return self.run("logs", "--no-color", "--tail", str(tail), timeout_s=60, check=False).stdout

    def down(self, volumes: bool) -> None:
        self.run("down", "--remove-orphans", *(["-v"] if volumes else []), "-t", "20", timeout_s=300)
