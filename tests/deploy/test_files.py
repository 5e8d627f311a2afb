"""The deploy files without a Docker engine: the compose file against the Compose Specification's JSON
schema and through a compose ``config`` run, and every command, module, port and path that the compose
file, the Dockerfile and the Serve config name checked against the project and its settings.

Schema source: ``compose-spec.json`` as vendored by the ``check-jsonschema`` PyPI package
(``check_jsonschema/builtin_schemas/vendor/compose-spec.json``, from the compose-spec project's
``schema/compose-spec.json``; its builtin name is ``vendor.compose-spec``). The ``config`` check is
``podman-compose --dry-run config`` (the podman-compose PyPI package), which parses, interpolates and
normalises the file without any container engine.
"""

from __future__ import annotations

import argparse
import copy
import importlib
import importlib.resources
import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
import yaml

from tests.pipelines.conftest import REPO

DEPLOY = REPO / "deploy"
COMPOSE = DEPLOY / "docker-compose.yml"
# Placeholder secrets for the interpolation of ${VAR:?} (the file refuses to render without them).
SECRETS = {"RAY_AUTH_TOKEN": "test-token-0123456789abcdef", "POSTGRES_PASSWORD": "test-password",
           "RADARSEG_API_KEYS": json.dumps({"key-test-0123456789abcdef": "acme"})}
SERVE_MISSING = "Ray Serve's dependencies (ray[serve]) are not installed"
INTERPOLATION = re.compile(r"\$\{(\w+)(?::?[-?])?([^}]*)\}")


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _interpolate(value: str, env: dict[str, str]) -> str:
    """Compose's ``${VAR}``, ``${VAR:-default}`` and ``${VAR:?error}`` (enough for our file)."""
    def one(match: re.Match) -> str:
        name, rest = match.group(1), match.group(2)
        if name in env:
            return env[name]
        token = match.group(0)
        if ":?" in token:
            raise KeyError(f"{name} must be set: {rest}")
        return rest if ":-" in token else ""

    return INTERPOLATION.sub(one, value)


def _dockerfile_instructions() -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) of deploy/Dockerfile, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", "\n".join(line for line in DEPLOY.joinpath("Dockerfile").read_text().splitlines()
                                          if not line.lstrip().startswith("#")))
    out = []
    for line in text.splitlines():
        if line.strip():
            keyword, _, args = line.strip().partition(" ")
            out.append((keyword.upper(), args.strip()))
    return out


# --------------------------------------------------------------------------- schema and config checks
def test_compose_file_matches_the_compose_specification_schema():
    import jsonschema

    pytest.importorskip("check_jsonschema", reason="check-jsonschema (vendors the compose-spec schema) not installed")
    vendored = importlib.resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json"
    schema = json.loads(vendored.read_text())
    validator = jsonschema.Draft202012Validator(schema)
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(_compose())]
    assert not errors, errors
    # The validator does catch what the spec forbids (not a vacuous pass).
    broken = _compose()
    broken["services"]["api"]["healthcheck"]["intervall"] = "5s"
    broken["services"]["ray-head"]["shm_size"] = [2]
    messages = " ".join(e.message for e in validator.iter_errors(broken))
    assert "intervall" in messages and "[2]" in messages


def _podman_compose(env: dict[str, str]) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).parent / "podman-compose"
    if not exe.exists():
        pytest.skip("podman-compose (the compose `config` check) is not installed")
    clean = {k: v for k, v in os.environ.items() if k not in SECRETS}
    return subprocess.run([str(exe), "--dry-run", "-f", str(COMPOSE), "config"], cwd=REPO, env={**clean, **env},
                          capture_output=True, text=True, timeout=60)


def test_compose_config_renders_with_secrets_from_the_environment_only():
    proc = _podman_compose(SECRETS)
    assert proc.returncode == 0, proc.stderr
    rendered = yaml.safe_load(proc.stdout)
    assert set(rendered["services"]) == {"postgres", "ray-head", "ray-worker", "api"}
    api_env = rendered["services"]["api"]["environment"]
    assert api_env["RADARSEG_API_KEYS"] == SECRETS["RADARSEG_API_KEYS"]
    assert SECRETS["POSTGRES_PASSWORD"] in api_env["RADARSEG_LEDGER_URL"]
    assert rendered["services"]["ray-worker"]["environment"]["RAY_AUTH_TOKEN"] == SECRETS["RAY_AUTH_TOKEN"]
    # Without a secret the file refuses to render.
    missing = _podman_compose({k: v for k, v in SECRETS.items() if k != "RAY_AUTH_TOKEN"})
    assert missing.returncode != 0 and "RAY_AUTH_TOKEN" in missing.stdout + missing.stderr


def test_no_secret_is_written_in_the_deploy_files():
    compose = COMPOSE.read_text()
    for name in ("RAY_AUTH_TOKEN", "POSTGRES_PASSWORD", "RADARSEG_API_KEYS"):
        for line in (ln for ln in compose.splitlines() if re.match(rf"\s*{name}:", ln)):
            assert f"${{{name}:?" in line, line  # always the environment's, required
    assert all(":?" in m.group(0) for m in re.finditer(r"\$\{POSTGRES_PASSWORD[^}]*\}", compose))
    for keyword, args in _dockerfile_instructions():
        if keyword in ("ENV", "ARG"):
            assert not re.search(r"(?i)(password|secret|api_keys|auth_token|ledger_url)", args), args
    serve = (DEPLOY / "serve.yaml").read_text()
    assert not re.search(r"(?i)(RADARSEG_API_KEYS|RADARSEG_LEDGER_URL|PASSWORD|RAY_AUTH_TOKEN)\s*:", serve)


# --------------------------------------------------------------------------- the compose file vs the project
def test_compose_services_ports_health_checks_and_dependencies():
    services = _compose()["services"]
    head, worker, api = services["ray-head"], services["ray-worker"], services["api"]
    head_args = dict(a.split("=", 1) for a in head["command"] if a.startswith("--") and "=" in a)
    published = {p.rsplit(":", 1)[-1] for p in head["ports"]}
    assert head_args["--port"] == "6379" and "6379" in head["expose"]
    assert head_args["--dashboard-port"] == "8265" and head_args["--ray-client-server-port"] == "10001"
    assert {"8265", "10001"} <= published
    assert "name" not in _compose()  # a Compose v2 key that Compose 1.29 refuses
    assert any(a == "--address=ray-head:6379" for a in worker["command"]) and head["hostname"] == "ray-head"
    for service in (head, worker):
        assert service["environment"]["RAY_AUTH_MODE"] == "token" and service["environment"][
            "RAY_USAGE_STATS_ENABLED"] == "0"
        assert service["shm_size"]
    # Scalable services have no fixed name and no single fixed host port.
    for name in ("ray-worker", "api"):
        assert "container_name" not in services[name]
    assert "ports" not in worker
    assert [p.rsplit(":", 1)[-1] for p in api["ports"]] == ["8000"]
    assert "-" in _interpolate(api["ports"][0], {}).split(":")[0]  # a range of host ports, one per replica
    published = {_interpolate(p, {}).rsplit(":", 2)[-2] for p in head["ports"]}
    assert {"8265", "10001"} <= published  # the defaults of the host-side variables
    for name, service in services.items():
        assert "healthcheck" in service, name
        for dependency, condition in service.get("depends_on", {}).items():
            assert condition["condition"] == "service_healthy" and "healthcheck" in services[dependency]
    assert worker["depends_on"] == {"ray-head": {"condition": "service_healthy"}}
    assert api["depends_on"] == {"postgres": {"condition": "service_healthy"}}


def test_compose_commands_exist_and_parse():
    from ray.scripts.scripts import healthcheck, start

    from pipelines.cli import build_parser

    services = _compose()["services"]
    ray_flags = {opt for param in start.params for opt in param.opts}
    for name in ("ray-head", "ray-worker"):
        command = [_interpolate(a, {}) for a in services[name]["command"]]
        assert command[:2] == ["ray", "start"]
        for arg in command[2:]:
            assert arg.split("=", 1)[0] in ray_flags, (name, arg)
    test = services["ray-head"]["healthcheck"]["test"]
    assert test[1:3] == ["ray", "health-check"] and set(test[3::2]) <= {o for p in healthcheck.params for o in p.opts}

    api_command = services["api"]["command"]
    assert api_command[0] == "radarseg"
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert scripts["radarseg"] == "pipelines.cli:main"
    args = build_parser().parse_args(api_command[1:])
    assert (args.command, args.host, args.port) == ("serve", "0.0.0.0", 8000)


def test_compose_paths_exist_and_volumes_are_shared():
    compose = _compose()
    services = compose["services"]
    for name in ("ray-head", "ray-worker", "api"):
        build = services[name]["build"]
        context = (COMPOSE.parent / build["context"]).resolve()
        assert context == REPO and (context / build["dockerfile"]).is_file()
        mounts = {m.split(":")[1]: m.split(":")[0] for m in services[name]["volumes"]}
        assert mounts["/data"] == "radarseg-data" and mounts["/app/checkpoints"] == "../checkpoints"
        assert services[name]["image"] == services["api"]["image"]  # one image for every role
    assert set(compose["volumes"]) == {"radarseg-data", "postgres-data"}
    for name in ("ray-worker", "api"):
        test = services[name]["healthcheck"]["test"]
        assert test[1] == "python" and test[2] == "/app/deploy/healthcheck.py"
        assert (REPO / "deploy" / "healthcheck.py").is_file()


def test_compose_environment_is_valid_service_settings(monkeypatch):
    """The API's environment, rendered, builds Settings (names exist, values validate, binds 0.0.0.0 with keys)."""
    from service.settings import Settings

    services = _compose()["services"]
    api = services["api"]
    for source in (api["environment"], services["ray-head"]["environment"]):
        for name in (n for n in source if n.startswith("RADARSEG_")):
            assert name.removeprefix("RADARSEG_").lower() in Settings.model_fields, name
    for name, value in api["environment"].items():
        if value is not None:  # a name alone passes the shell's value through, or nothing
            monkeypatch.setenv(name, _interpolate(str(value), SECRETS))
    monkeypatch.setenv("RADARSEG_HOST", "0.0.0.0")  # what `--host 0.0.0.0` sets in `radarseg serve`
    settings = Settings()
    assert settings.ledger_url.startswith("postgresql+psycopg://radarseg:")
    assert settings.tenants == ["acme"] and str(settings.data_dir).startswith("/data/")
    assert int(api["command"][api["command"].index("--port") + 1]) == settings.port
    monkeypatch.delenv("RADARSEG_API_KEYS")
    with pytest.raises(ValueError, match="without API keys"):
        Settings()


# --------------------------------------------------------------------------- the Dockerfile vs the project
def test_dockerfile_base_torch_user_health_check_and_command():
    instructions = _dockerfile_instructions()
    args = dict(a.split("=", 1) for k, a in instructions if k == "ARG" and "=" in a)
    pyproject = tomllib.loads((REPO / "pyproject.toml").read_text())
    # the official base by default, another (an offline stand-in) by build argument; no frontend image to pull
    assert args["PYTHON_IMAGE"] == "python:3.11-slim" and "3.11" in pyproject["project"]["requires-python"]
    assert not DEPLOY.joinpath("Dockerfile").read_text().startswith("# syntax=")
    assert [a for k, a in instructions if k == "FROM"] == ["${PYTHON_IMAGE} AS build", "${PYTHON_IMAGE}"]
    assert f"torch=={args['TORCH_VERSION']}" in pyproject["project"]["dependencies"]
    assert args["TORCH_INDEX_URL"].endswith("/cpu") and (REPO / args["TORCH_WHEELS"]).is_dir()
    final = instructions[max(i for i, (k, _) in enumerate(instructions) if k == "FROM"):]
    assert not any("g++" in a for k, a in final if k == "RUN")  # the compiler stays in the build stage
    for keyword, arguments in instructions:
        if keyword == "COPY" and not arguments.startswith("--from="):
            *sources, _ = shlex.split(arguments.replace("${TORCH_WHEELS}", args["TORCH_WHEELS"]))
            for source in sources:
                assert (REPO / source).exists(), source
    users = [a for k, a in instructions if k == "USER"]
    assert users and users[-1] not in ("root", "0")
    exposed = {p for k, a in instructions if k == "EXPOSE" for p in a.split()}
    assert exposed == {"8000", "6379", "8265", "10001"}
    health = next(a for k, a in instructions if k == "HEALTHCHECK")
    assert '"/app/deploy/healthcheck.py", "api"' in health
    command = json.loads(next(a for k, a in instructions if k == "CMD"))
    assert command == _compose()["services"]["api"]["command"][:len(command)]
    env = " ".join(a for k, a in final if k == "ENV")
    assert "RAY_AUTH_MODE=token" in env and "RAY_USAGE_STATS_ENABLED=0" in env
    # at the context's root, where every builder reads it (BuildKit, the classic builder, Compose 1.29)
    ignore = (REPO / ".dockerignore").read_text().splitlines()
    assert "**" in ignore  # the build context is limited to what the COPY lines name
    for keyword, arguments in instructions:
        if keyword == "COPY" and not arguments.startswith("--from="):
            for source in shlex.split(arguments.replace("${TORCH_WHEELS}", args["TORCH_WHEELS"]))[:-1]:
                source = source.rstrip("/")
                if source.startswith("models/sparse"):
                    source = "models"
                assert f"!{source.rstrip('/')}" in ignore or f"!{source.rstrip('/')}/" in ignore, source


def test_healthcheck_script_roles(tmp_path):
    spec = importlib.util.spec_from_file_location("healthcheck", DEPLOY / "healthcheck.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["api", "--url", "http://127.0.0.1:9"]) == 1  # nothing listens on the discard port
    proc = tmp_path / "proc"
    (proc / "123").mkdir(parents=True)
    (proc / "123" / "stat").write_text("123 (raylet) S 1 123 123 0")
    (proc / "124").mkdir()
    (proc / "124" / "stat").write_text("124 (python) S 1 124 124 0")
    assert module.raylet_running(proc)
    (proc / "123" / "stat").write_text("123 (raylet) Z 1 123 123 0")
    assert not module.raylet_running(proc)


# --------------------------------------------------------------------------- the Serve config vs the project
def test_serve_config_validates_and_points_at_the_service():
    pytest.importorskip("ray.serve", reason=SERVE_MISSING)
    from ray.serve.schema import ServeDeploySchema

    from service.settings import Settings

    config = yaml.safe_load((DEPLOY / "serve.yaml").read_text())
    schema = ServeDeploySchema.model_validate(config)
    (app,) = schema.applications
    module_name, attr = app.import_path.split(":")
    module = importlib.import_module(module_name)
    assert callable(getattr(module, attr))
    (deployment,) = app.deployments
    assert deployment.name == module.DEPLOYMENT_NAME
    env = app.runtime_env["env_vars"]
    for name in (n for n in env if n.startswith("RADARSEG_")):
        assert name.removeprefix("RADARSEG_").lower() in Settings.model_fields, name
    assert deployment.max_ongoing_requests <= int(env["RADARSEG_REPLICAS"]) + int(env["RADARSEG_MAX_QUEUE"])
    scaling = deployment.autoscaling_config
    assert scaling["min_replicas"] <= scaling["initial_replicas"] <= scaling["max_replicas"]
    assert env["RADARSEG_HOST"] == config["http_options"]["host"]  # keys required when the proxy binds 0.0.0.0
    bad = copy.deepcopy(config)
    bad["applications"][0]["deployments"][0]["max_ongoing_requests"] = "many"
    with pytest.raises(ValueError):
        ServeDeploySchema.model_validate(bad)


def test_serve_application_builder_checks_its_arguments():
    pytest.importorskip("ray.serve", reason=SERVE_MISSING)
    from service.main import build_app
    from service.ray_serve import RadarsegService

    assert build_app({"settings": {"max_queue": 3}}) is not None
    with pytest.raises(ValueError, match="unknown application arguments"):
        build_app({"replicas": 2})
    with pytest.raises(ValueError, match="mapping"):
        build_app({"settings": ["max_queue"]})
    assert RadarsegService.name == "radarseg"


def test_every_module_the_deploy_docs_name_imports():
    """Modules run by the compose file, the Serve config and deploy/README.md exist."""
    text = "\n".join(p.read_text() for p in (DEPLOY / "README.md", COMPOSE, DEPLOY / "serve.yaml"))
    modules = set(re.findall(r"python -m ((?:pipelines|service)(?:\.\w+)+)", text))
    modules |= {m.split(":")[0] for m in re.findall(r"\b(service\.\w+:\w+)", text)}
    assert {"pipelines.datasets.preprocess", "pipelines.inference.segment_batch", "service.main"} <= modules
    for name in modules:
        assert importlib.util.find_spec(name) is not None, name
    parser = argparse.ArgumentParser()
    from pipelines.inference.segment_batch import add_arguments

    add_arguments(parser)
    for line in re.findall(r"python -m pipelines\.inference\.segment_batch ([^\n`]+)", text):
        options = {tok for tok in line.split() if tok.startswith("--")}
        known = {o for a in parser._actions for o in a.option_strings}
        assert options <= known, options - known
