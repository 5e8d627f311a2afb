"""Where the compiled sparse kernels are cached: one build per environment (interpreter, torch and its C++ ABI,
compiler and flags, sources, CPU), so that two clones with their own venvs on one machine never share, overwrite or
rebuild each other's kernels. Nothing is compiled here: the tests ask each interpreter where its build would go."""

from __future__ import annotations

import json
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
import torch

from models.sparse import compiled

REPO = Path(__file__).resolve().parents[3]
WHERE = ("import json\n"
         "from models.sparse import compiled\n"
         "print(json.dumps({'directory': str(compiled.build_directory('radarseg_sparse', 'native')),\n"
         "                  'environment': compiled.build_environment('native')}))\n")


def _second_venv(folder: Path) -> Path:
    """A second venv on this machine, as a second clone's would be, with this venv's packages (a .pth file names
    them, so nothing is installed). Its interpreter."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", "--system-site-packages", str(folder)],
                   check=True, timeout=120)
    python = folder / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True, timeout=60).stdout.strip()
    (Path(purelib) / "radarseg-parent-venv.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


def _where(python: Path | str, cache: Path) -> dict:
    """Where `python`'s build of the kernels would be cached under `cache`, and what it would be built for."""
    env = {"TORCH_EXTENSIONS_DIR": str(cache), "PATH": "/usr/bin:/bin"}
    done = subprocess.run([str(python), "-c", WHERE], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout)


def test_two_venvs_on_one_machine_build_into_their_own_folders(tmp_path):
    cache = tmp_path / "extensions"
    first = _where(sys.executable, cache)
    second = _where(_second_venv(tmp_path / "second-venv"), cache)
    assert first["directory"] != second["directory"]
    assert Path(first["directory"]).parent == Path(second["directory"]).parent == cache
    differing = {key for key in first["environment"] if first["environment"][key] != second["environment"][key]}
    assert {"interpreter", "prefix"} <= differing
    assert first["environment"]["torch"] == second["environment"]["torch"]  # the same torch, still two builds
    # each interpreter finds its own folder again: the first venv's build is reused, not rebuilt
    assert _where(sys.executable, cache)["directory"] == first["directory"]

    # the second venv's build, once made, tells the first why it builds anew
    built = Path(second["directory"])
    built.mkdir(parents=True)
    (built / compiled.MANIFEST).write_text(json.dumps(second["environment"]))
    reason = compiled.build_reason(Path(first["directory"]), first["environment"])
    assert "other environments" in reason and "interpreter" in reason and "sources" not in reason


@pytest.mark.parametrize("part", ["torch_version", "cxx11_abi", "compiler", "flags", "interpreter", "clone"])
def test_the_build_key_changes_with_each_part_of_the_environment(monkeypatch, tmp_path, part):
    before = compiled.build_key("native")
    if part == "clone":  # the same sources in a second clone: torch's build names them by path
        copies = []
        for source in compiled.SOURCES:
            copies.append(tmp_path / source.name)
            copies[-1].write_bytes(source.read_bytes())
        assert compiled.build_key("native", tuple(copies)) != before
        return
    if part == "torch_version":
        monkeypatch.setattr(torch, "__version__", torch.__version__ + ".other")
    elif part == "cxx11_abi":
        monkeypatch.setattr(torch._C, "_GLIBCXX_USE_CXX11_ABI", not torch._C._GLIBCXX_USE_CXX11_ABI)
    elif part == "compiler":
        monkeypatch.setattr(compiled, "compiler_identity", lambda: "/usr/bin/clang++: clang version 99")
    elif part == "flags":
        monkeypatch.setattr(compiled, "CFLAGS", (*compiled.CFLAGS, "-ffast-math"))
    else:
        monkeypatch.setattr(sys, "executable", "/elsewhere/venv/bin/python")
    assert compiled.build_key("native") != before
    assert compiled.build_key("avx2") != compiled.build_key("native")


def test_a_first_build_and_an_unfinished_one_say_so(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    directory = compiled.build_directory("radarseg_sparse")
    assert directory.parent == tmp_path
    assert compiled.build_reason(directory, compiled.build_environment()) == "no build of it is cached yet"
    directory.mkdir()
    (directory / "build.ninja").write_text("")
    assert "did not finish" in compiled.build_reason(directory, compiled.build_environment())

