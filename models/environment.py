"""Every environment variable that radar/, models/, pipelines/, benchmarks/ and experiments/ read, in one settings
object: :class:`Environment`, each field declared with its variable. ``environment()`` reads them when called (jobs
and tests set them at run time), and nothing else outside this module and ``service/settings.py`` reads the
environment (``tests/test_environment.py``). The service's own ``Settings`` declares the variables of this object
that it serves (``Settings.models_environment``) and exports them before any model loads.

Writes stay where they are: a job sets variables for the processes it starts (Ray's ``RAY_AUTH_MODE``, the
service's ``RADARSEG_MODELS``, ``PATH`` for torch's ``ninja``)."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any


def _variable(name: str, default: Any, parse: Callable[[str], Any], what: str) -> Any:
    """A field read from the environment variable ``name`` by ``parse`` (``default`` when it is not set)."""
    return field(default=default, metadata={"variable": name, "parse": parse, "what": what})


def _flag(text: str) -> bool:
    return text not in ("", "0")


def _choice(text: str) -> str:
    return text.strip().lower() or "auto"


def _path(text: str) -> Path | None:
    return Path(text).expanduser() if text else None


def _text(text: str) -> str | None:
    return text or None


@dataclass(frozen=True)
class Environment:
    """What the environment sets (the defaults: what an unset variable means)."""

    smoke: bool = _variable("RADARSEG_SMOKE", False, _flag,
                            "any value but empty or 0: every job runs its command on tiny sizes (pipelines.jobs)")
    sparse_kernels: str = _variable("RADARSEG_SPARSE_KERNELS", "auto", _choice,
                                    "the sparse convolutions' kernels: auto, compiled or reference (models.sparse)")
    sparse_engine: str | None = _variable("RADARSEG_SPARSE_ENGINE", None, str,
                                          "the earlier name of RADARSEG_SPARSE_KERNELS: refused, naming it")
    onnx_cache: Path | None = _variable("RADARSEG_ONNX_CACHE", None, _path,
                                        "where the onnx engines' exports are kept (unset: ~/.cache/radarseg/onnx)")
    onnx_cache_key_file: Path | None = _variable(
        "RADARSEG_ONNX_CACHE_KEY_FILE", None, _path,
        "the secret that seals the ONNX exports (unset: ~/.config/radarseg/onnx-cache.key)")
    int8_cache: Path | None = _variable("RADARSEG_INT8_CACHE", None, _path,
                                        "where the torch engine's int8 calibrations are kept "
                                        "(unset: ~/.cache/radarseg/int8)")
    torch_extensions_dir: Path | None = _variable(
        "TORCH_EXTENSIONS_DIR", None, _path,
        "where the compiled sparse kernels are built (torch's variable; unset: ~/.cache/radarseg/extensions)")
    cxx: str | None = _variable("CXX", None, _text,
                                "the C++ compiler building the compiled sparse kernels (unset: c++)")
    ray_address: str | None = _variable("RAY_ADDRESS", None, _text,
                                        "the Ray cluster a job joins (Ray's variable; unset: an embedded local Ray)")

    @classmethod
    def read(cls, environ: Mapping[str, str] | None = None) -> Environment:
        """The settings ``environ`` (default: this process's environment) gives."""
        environ = os.environ if environ is None else environ
        return cls(**{f.name: f.metadata["parse"](environ[f.metadata["variable"]])
                      for f in fields(cls) if f.metadata["variable"] in environ})

    @classmethod
    def variables(cls) -> dict[str, str]:
        """Field name -> the environment variable it is read from."""
        return {f.name: f.metadata["variable"] for f in fields(cls)}


def environment() -> Environment:
    """This process's environment, read now."""
    return Environment.read()
