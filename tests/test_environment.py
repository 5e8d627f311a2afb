"""Every environment variable outside service/ is read in one settings object (models/environment.py): no other
file of radar/, models/, pipelines/, benchmarks/ or experiments/ reads ``os.environ`` or ``getenv`` (read from the
source with ast). Writes stay allowed: setting a variable (``os.environ[K] = V``, ``setdefault``, ``update``,
``pop``) and copying the environment for a child process (``{**os.environ, ...}``, ``.copy()``)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from models.environment import Environment

REPO = Path(__file__).resolve().parents[1]
SCANNED = ("radar", "models", "pipelines", "benchmarks", "experiments")
SETTINGS_MODULE = Path("models/environment.py")
WRITES = {"setdefault", "update", "pop", "copy"}  # os.environ.<method>: a write or a child's copy, not a read
READS_IN_A_WRITE = {  # (file, variable read) -> why it is no setting
    ("models/sparse/compiled.py", "PATH"): "PATH gets ninja's folder in front of it, for torch's build subprocess",
}


def _environment_reads(path: Path) -> list[str]:
    """``line: source`` of each read of the environment in ``path``."""
    tree = ast.parse(path.read_text(), filename=str(path))
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    reads = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "os" and \
                any(alias.name in ("environ", "getenv") for alias in node.names):
            reads.append(f"{node.lineno}: {ast.unparse(node)}")
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "os" and \
                node.attr in ("getenv", "getenvb", "environb"):
            reads.append(f"{node.lineno}: {ast.unparse(parents[node])}")
        if not (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "os"
                and node.attr == "environ"):
            continue
        parent = parents[node]
        if isinstance(parent, ast.Subscript) and isinstance(parent.ctx, (ast.Store, ast.Del)):
            continue  # os.environ[K] = V
        if isinstance(parent, ast.Attribute) and parent.attr in WRITES:
            continue
        if isinstance(parent, ast.Dict) and any(key is None and value is node
                                                for key, value in zip(parent.keys, parent.values, strict=True)):
            continue  # {**os.environ, ...}: a child's environment
        call = parents.get(parent)
        if isinstance(parent, ast.Attribute) and parent.attr == "get" and isinstance(call, ast.Call) and \
                call.args and isinstance(call.args[0], ast.Constant) and \
                (path.relative_to(REPO).as_posix(), call.args[0].value) in READS_IN_A_WRITE:
            continue
        reads.append(f"{node.lineno}: {ast.unparse(parent)}")
    return reads


def test_no_environment_read_outside_the_settings_object():
    found = {}
    for package in SCANNED:
        for path in sorted((REPO / package).rglob("*.py")):
            if path.relative_to(REPO) != SETTINGS_MODULE and (reads := _environment_reads(path)):
                found[path.relative_to(REPO).as_posix()] = reads
    assert not found, f"read the environment through models.environment.environment(): {found}"


def test_the_scan_sees_each_kind_of_read(tmp_path, monkeypatch):
    monkeypatch.setattr(f"{__name__}.REPO", tmp_path)
    source = tmp_path / "reader.py"
    source.write_text("import os\nfrom os import getenv\na = os.environ.get('X')\nb = os.environ['Y']\n"
                      "c = 'Z' in os.environ\nd = os.getenv('W')\n"
                      "os.environ['V'] = '1'\nos.environ.setdefault('U', '0')\ne = {**os.environ, 'T': '1'}\n")
    assert sorted(int(line.split(":")[0]) for line in _environment_reads(source)) == [2, 3, 4, 5, 6]


def test_each_variable_is_parsed_as_its_readers_took_it():
    assert Environment.read({}) == Environment()
    assert Environment.read({"RADARSEG_SMOKE": "0"}).smoke is False
    assert Environment.read({"RADARSEG_SMOKE": ""}).smoke is False
    assert Environment.read({"RADARSEG_SMOKE": "yes"}).smoke is True
    assert Environment.read({"RADARSEG_SPARSE_KERNELS": " Compiled "}).sparse_kernels == "compiled"
    assert Environment.read({"RADARSEG_SPARSE_KERNELS": ""}).sparse_kernels == "auto"
    assert Environment.read({"RADARSEG_SPARSE_ENGINE": ""}).sparse_engine == ""  # set, even empty: refused
    assert Environment.read({"RADARSEG_ONNX_CACHE": "~/c"}).onnx_cache == Path.home() / "c"
    assert Environment.read({"RADARSEG_ONNX_CACHE_KEY_FILE": ""}).onnx_cache_key_file is None
    assert Environment.read({"TORCH_EXTENSIONS_DIR": "/x"}).torch_extensions_dir == Path("/x")
    assert Environment.read({"RAY_ADDRESS": ""}).ray_address is None
    assert Environment.read({"CXX": "clang++"}).cxx == "clang++" and Environment.read({"CXX": ""}).cxx is None


def test_the_process_environment_is_read_when_asked(monkeypatch):
    from models.environment import environment
    from pipelines.jobs import smoke_mode

    monkeypatch.setenv("RADARSEG_SMOKE", "1")
    assert environment().smoke and smoke_mode()
    monkeypatch.setenv("RADARSEG_SMOKE", "0")
    assert not environment().smoke and not smoke_mode()


def test_the_service_exports_only_variables_of_the_settings_object():
    settings = pytest.importorskip("service.settings")
    exported = settings.Settings(onnx_cache="/c", onnx_cache_key_file="/k", sparse_kernels="reference")
    assert set(exported.models_environment()) <= set(Environment.variables().values())
