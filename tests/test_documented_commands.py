"""Every documented command runs as written, so the docs cannot drift from the code: the ``bash`` blocks of
README.md, deploy/README.md and every page of the documentation site (docs/**/*.md).

The commands are read out of the documents' ``bash`` blocks (continuation lines joined, comments dropped) and each
document's commands run in order in its own fresh working directory laid out like a clone (the repository's code
and ``.venv`` linked, the shipped checkpoints copied, since some commands overwrite them), so every page stands on
its own: a page that needs what another page makes says so and runs the (smoke-sized) commands itself.
Sizes are tiny through the documented
smoke mode (``RADARSEG_SMOKE=1``: every job caps its sequences, frames, epochs, steps and frames scored) and the
service's documented ``RADARSEG_WARMUP=false``; the command lines are never edited but for one thing: a page's
loopback ports (8000, ``--port 8080``) are this machine's, which parallel tests share, so each page's runner maps
every documented port to a free one of its own, in the commands and in ``RADARSEG_PORT`` for a server started
without ``--port`` (the documented default, 8000). ``radarseg`` and
``python -m pipelines.*`` commands run in this process (one torch import for all); the others as processes.

Only the commands matched by :data:`SKIPS` are not run, each with its reason, which the run prints; a rule that
matches no command fails the check, as does a command that is neither run nor skipped. Blocks of other languages
(```text, ```console, ```toml) are examples and output, never run.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = ("README.md", "deploy/README.md",
             *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").rglob("*.md") if "hooks" not in p.parts))

# (pattern on the command line, reason): the only commands not run.
SKIPS: tuple[tuple[str, str], ...] = (
    (r"^make test$", "the test suite itself"),
    (r"^docker\b", "needs a Docker engine"),
    (r"^export (RAY_AUTH_TOKEN|POSTGRES_PASSWORD|RADARSEG_API_KEYS|RAY_AUTH_MODE)=", "the compose cluster's "
     "secrets (needs a Docker engine)"),
    (r"^curl .*localhost:(8000|8100)", "the compose services (needs a Docker engine)"),
    (r"^ray job (submit|list) --address http://localhost:8265", "the compose cluster's jobs API (needs a Docker "
     "engine)"),
    (r"carrada:/data/Carrada", "needs a CARRADA download"),
    (r"^ray start --head", "starts a persistent Ray head on the default ports, which only `ray stop` (every Ray "
     "on the machine) ends: the same job submission runs in tests/deploy/test_topology.py on free ports"),
    (r"^ray job submit --address http://127.0.0.1:8265", "needs the Ray head above (tests/deploy/test_topology.py)"),
    (r"serve run deploy/serve.yaml", "a persistent local Ray Serve on port 8000: the same "
     "config is deployed in tests/deploy/test_topology.py"),
    (r"^\.venv/bin/mkdocs build", "the documentation site: tests/test_docs_site.py builds it with --strict"),
    (r"my_radar\.toml|data/mine|runs/mine|model=myradar", "the own-radar path: run as written, and checked step by "
     "step, by tests/test_own_radar_guide.py"),
)
SMOKE_ENV = {"RADARSEG_SMOKE": "1", "RADARSEG_WARMUP": "false", "RAY_AUTH_MODE": "disabled",
             "RAY_USAGE_STATS_ENABLED": "0"}
LINKED = (".venv", "process", "radar", "models", "pipelines", "service", "deploy", "benchmarks", "docs", "Makefile",
          "pyproject.toml", "README.md", "tests", ".gitignore", ".rayignore", "mkdocs.yml")


@dataclass(frozen=True)
class Command:
    document: str
    block: int  # the bash block's index in the document
    line: int  # first line in the document
    words: tuple[str, ...]  # as the shell splits it, comment dropped

    @property
    def text(self) -> str:
        return " ".join(self.words)

    def __str__(self) -> str:
        return f"{self.document}:{self.line}: {self.text}"


SHELL_SYNTAX = ("&", ";", "|", ">", "<", "&&", "||", "$(")


def _block_commands(document: str, block: int, lines: list[tuple[int, str]]) -> list[Command]:
    """One block's commands: a command per line as the shell joins them, or the whole block as one ``bash -e``
    script when it needs a shell (a background job, a pipe, a redirection, a quoted string over several lines)."""
    commands, pending, start = [], "", 0
    try:
        for number, line in lines:
            if not pending:
                start = number
            if line.endswith("\\"):  # a continuation line, as the shell joins it
                pending += line[:-1]
                continue
            lexer = shlex.shlex(pending + line, posix=True, punctuation_chars=True)
            lexer.commenters = "#"
            tokens = list(lexer)
            if any(token in SHELL_SYNTAX or token.startswith("$(") for token in tokens):
                raise ValueError("shell syntax")
            words = tuple(shlex.split(pending + line, comments=True))
            pending = ""
            if words:
                commands.append(Command(document, block, start, words))
    except ValueError:  # unbalanced quotes on one line, or shell syntax: the block is a script
        script = "\n".join(line for _, line in lines)
        return [Command(document, block, lines[0][0], ("bash", "-e", "-o", "pipefail", "-c", script))]
    return commands


def documented_commands(documents: tuple[str, ...] = DOCUMENTS) -> list[Command]:
    """The commands of the documents' ``bash`` blocks, in order."""
    commands = []
    for document in documents:
        in_block, block, lines = False, 0, []
        for number, line in enumerate((REPO / document).read_text().splitlines(), 1):
            if line.startswith("```"):
                if in_block and lines:
                    commands.extend(_block_commands(document, block, lines))
                in_block, lines = not in_block and line.strip() == "```bash", []
                block += 1
                continue
            if in_block:
                lines.append((number, line))
    return commands


def skip_reason(command: Command) -> str | None:
    return next((reason for pattern, reason in SKIPS if re.search(pattern, command.text)), None)


def test_every_documented_command_is_run_or_skipped_for_a_stated_reason():
    commands = documented_commands()
    assert len(commands) > 30, [str(c) for c in commands]
    for pattern, _ in SKIPS:
        assert any(re.search(pattern, c.text) for c in commands), f"skip rule {pattern!r} matches no command"
    placeholders = [str(c) for c in commands if skip_reason(c) is None
                    and re.search(r"((?<!\[)\.\.\.|STORE\.zarr|\bDIR\b|<[a-z ]+>|\bD\.pt\b|\bCUBE\.npy\b)", c.text)]
    assert not placeholders, f"commands with placeholders cannot run as written: {placeholders}"


def _free(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) != 0


DEFAULT_PORT = 8000  # `radarseg serve` without --port, as the service guide documents
LOOPBACK_PORT = re.compile(r"(?<![\w.])(127\.0\.0\.1:|localhost:|--port[ =])(\d{2,5})\b")


class Runner:
    """Runs the commands of the documents in order in ``root``. A server (``radarseg serve``, ``python -m
    service``) stays up, on its port, until the end of its block or the next server on that port."""

    def __init__(self, root: Path):
        self.root = root
        self.servers: dict[int, subprocess.Popen] = {}
        self.block: tuple[str, int] | None = None
        self.ports: dict[int, int] = {}  # documented port -> this runner's free port
        self.env = {**os.environ, **SMOKE_ENV, "PATH": f"{root / '.venv' / 'bin'}{os.pathsep}{os.environ['PATH']}"}

    def run(self, command: Command) -> str | None:
        """``None`` on success, else what went wrong (one paragraph)."""
        if (command.document, command.block) != self.block:
            self.stop()
            self.block = (command.document, command.block)
        words = self._mapped(list(command.words))
        program = Path(words[0]).name
        if words[1:2] == ["serve"] and program == "radarseg" or words[1:3] == ["-m", "service"]:
            return self._serve(words)
        if program == "radarseg":
            return self._in_process(lambda: _cli_main(words[1:]))
        if program == "python" and words[1] == "-m" and words[2].startswith("pipelines."):
            return self._in_process(lambda: _run_module(words[2], words[3:]))
        if words[:2] == ["make", "demo"]:
            dry = subprocess.run(["make", "-n", "demo"], cwd=self.root, capture_output=True, text=True, env=self.env)
            if dry.returncode or ".venv/bin/radarseg demo --out out/demo" not in dry.stdout:
                return f"make -n demo: {dry.stdout}{dry.stderr}"
            return self._in_process(lambda: _cli_main(["demo", "--out", "out/demo"]))
        done = subprocess.run(words, cwd=self.root, capture_output=True, text=True, env=self.env, timeout=300)
        if done.returncode:
            return f"exit {done.returncode}: {done.stdout[-2000:]}{done.stderr[-2000:]}"
        if program == "curl" and "/segment" in command.text and "objects" not in json.loads(done.stdout):
            return f"no objects in the answer: {done.stdout[:500]}"
        return None

    def _in_process(self, call) -> str | None:  # noqa: ANN001
        cwd = os.getcwd()
        saved = {k: os.environ.get(k) for k in SMOKE_ENV}
        os.environ.update(SMOKE_ENV)
        os.chdir(self.root)
        try:
            code = call()
        except SystemExit as exc:  # argparse
            code = exc.code
        finally:
            os.chdir(cwd)
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        return None if code == 0 else f"exit {code}"

    def port(self, documented: int) -> int:
        """The free loopback port this runner uses where the page says ``documented``."""
        from pipelines.demo.serve_process import free_port

        if documented not in self.ports:
            self.ports[documented] = free_port()
        return self.ports[documented]

    def url(self, documented: int = DEFAULT_PORT) -> str:
        return f"http://127.0.0.1:{self.port(documented)}"

    def _mapped(self, words: list[str]) -> list[str]:
        """``words`` with every documented loopback port (``127.0.0.1:N``, ``localhost:N``, ``--port N``) mapped,
        in a script's text too."""
        mapped = [LOOPBACK_PORT.sub(lambda m: f"{m[1]}{self.port(int(m[2]))}", word) for word in words]
        for i, word in enumerate(mapped[:-1]):
            if word == "--port" and mapped[i + 1].isdigit():
                mapped[i + 1] = str(self.port(int(mapped[i + 1])))
        return mapped

    def _serve(self, words: list[str]) -> str | None:
        from pipelines.demo.serve_process import wait_ready

        port = int(words[words.index("--port") + 1]) if "--port" in words else self.port(DEFAULT_PORT)
        self._stop(port)
        if not _free(port):
            return f"port {port} (a free one a moment ago) is taken: another process bound it"
        log_path = self.root / f"server-{port}-{len(words)}.log"
        with log_path.open("w") as log:
            program = self.root / ".venv" / "bin" / Path(words[0]).name
            self.servers[port] = subprocess.Popen([str(program), *words[1:]], cwd=self.root,
                                                  env={**self.env, "RADARSEG_PORT": str(port)},
                                                  stdout=log, stderr=subprocess.STDOUT)
        try:
            wait_ready(f"http://127.0.0.1:{port}", self.servers[port], log_path, timeout_s=240)
        except RuntimeError as exc:
            return f"did not become ready: {exc}"
        return None

    def _stop(self, port: int) -> None:
        from pipelines.demo.serve_process import stop_process

        server = self.servers.pop(port, None)
        if server is not None:
            stop_process(server)

    def stop(self) -> None:
        for port in list(self.servers):
            self._stop(port)


def _cli_main(argv: list[str]) -> int:
    from pipelines.cli import main

    return main(argv)


def _run_module(name: str, argv: list[str]) -> int:
    from pipelines.jobs import run_module

    return run_module(name, argv)


def make_clone(root: Path) -> Path:
    """``root`` laid out like a fresh clone after `make venv`: code and .venv linked, checkpoints copied."""
    root.mkdir(parents=True, exist_ok=True)
    for name in LINKED:
        if (REPO / name).exists():
            (root / name).symlink_to(REPO / name)
    shutil.copytree(REPO / "checkpoints", root / "checkpoints")
    return root


DOCUMENTS_WITH_COMMANDS = tuple(d for d in DOCUMENTS if documented_commands((d,)))
# The jobs that start an embedded Ray (preprocess, segment-batch, training, the demo): a page running one is a Ray
# test (one Ray at a time, on one worker); the others spread over the workers (their ports are their own).
STARTS_RAY = re.compile(r"\b(preprocess|segment-batch|train|train-baseline|slim-sweep|demo|ray job)\b")


def _page(document: str):  # noqa: ANN202 (a pytest parameter)
    runs_ray = any(STARTS_RAY.search(c.text) for c in documented_commands((document,)) if skip_reason(c) is None)
    return pytest.param(document, marks=pytest.mark.ray) if runs_ray else document


@pytest.mark.slow
@pytest.mark.parametrize("document", [_page(d) for d in DOCUMENTS_WITH_COMMANDS])
def test_every_documented_command_runs_as_written(document, tmp_path):
    runner = Runner(make_clone(tmp_path / "clone"))
    failures, ran, started = [], 0, time.perf_counter()
    try:
        for command in documented_commands((document,)):
            reason = skip_reason(command)
            if reason is not None:
                print(f"[ skipped] {command}\n           because: {reason}", file=sys.stderr)
                continue
            began = time.perf_counter()
            problem = runner.run(command)
            print(f"[{time.perf_counter() - began:6.1f} s] {command}", file=sys.stderr)
            ran += 1
            if problem is not None:
                failures.append(f"{command}\n    {problem}")
    finally:
        runner.stop()
    print(f"{document}: {ran} documented commands run in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    assert not failures, "documented commands that fail:\n" + "\n".join(failures)


def test_the_local_serve_run_line_gives_the_keys_its_0_0_0_0_replicas_need(monkeypatch):
    """deploy/README's `serve run deploy/serve.yaml`: the proxy binds 0.0.0.0 (serve.yaml), so the documented
    line must carry RADARSEG_API_KEYS, with which a replica's settings validate (and without which they refuse)."""
    import yaml

    from service.settings import Settings

    (command,) = [c for c in documented_commands() if "serve run deploy/serve.yaml" in c.text]
    env = dict(word.split("=", 1) for word in command.words[:command.words.index("serve")])
    replica_env = yaml.safe_load((REPO / "deploy" / "serve.yaml").read_text())["applications"][0]["runtime_env"]
    for name, value in {**replica_env["env_vars"], **env}.items():
        monkeypatch.setenv(name, str(value))
    assert Settings().host == "0.0.0.0" and Settings().api_keys
    monkeypatch.delenv("RADARSEG_API_KEYS")
    with pytest.raises(ValueError, match="without API keys"):
        Settings()
