"""The compiled sparse kernels: which kernels run the sparse convolutions, and the C++ extension they load.

Two sets of sparse kernels run `models.sparse.conv`'s convolutions: `reference` (pure PyTorch, any device and dtype)
and `compiled` (`csrc/sparse_conv.cpp`: gather-multiply kernels over the kernel map's neighbour table, float32 on
CPU; `csrc/kernel_maps.cpp`: every kernel map of a voxel pyramid in one pass). The setting (`set_kernels`, or the
environment variable `RADARSEG_SPARSE_KERNELS` read at first use) is one of:

- `auto` (default): compiled where they apply (CPU, float32) if they build, else reference with one warning;
- `compiled`: compiled where they apply; a failed build raises;
- `reference`: always the pure-PyTorch kernels.

The runtime (`--runtime torch|torch-int8|onnx|onnx-int8`, :mod:`models.runtime`) is another choice: the torch
runtimes run their sparse convolutions on this setting's kernels. The earlier names (the variable
`RADARSEG_SPARSE_ENGINE`, the values `native` and `torch`) are refused with the new ones.

The extension is built on first use with torch's extension machinery (g++ and ninja) and cached under
`$TORCH_EXTENSIONS_DIR/` or `~/.cache/radarseg/extensions/`, in a folder named by a hash of everything the
compiled code depends on (`build_environment`): the sources and where they are, the compiler and its flags, the
interpreter (its path and prefix: each venv has its own build), torch's version, location and C++ ABI, Python's
version and the CPU's instruction-set flags (it is compiled with `-march=native`, so a cache shared between machines
of different kinds never serves foreign code). Two clones on one machine, with their own venvs or one, therefore
never rebuild over each other's kernels. Each build folder keeps what it was built for in `build.json`, and a build
logs that it is building and why (which of those differs from the builds already cached). torch's loader holds a
file lock while it builds, so concurrent processes build it once.
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import json
import logging
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from models.environment import environment

logger = logging.getLogger(__name__)

KERNELS = ("auto", "compiled", "reference")
RENAMED = {"native": "compiled", "torch": "reference"}  # earlier names -> today's
KERNELS_ENV = "RADARSEG_SPARSE_KERNELS"
OLD_KERNELS_ENV = "RADARSEG_SPARSE_ENGINE"  # refused with the new name
CSRC = Path(__file__).parent / "csrc"
SOURCES = (CSRC / "sparse_conv.cpp", CSRC / "kernel_maps.cpp")
"""The extension's C++ files: the convolution kernels (and the module's bindings), and a pyramid's kernel maps."""
HEADERS = (CSRC / "micro_kernel.h",)
"""The headers the extensions' C++ files include (the micro-kernel this one shares with `models.sparse.int8`'s):
hashed into every build key with the sources."""
CFLAGS = ("-O3", "-march=native", "-fopenmp")
LDFLAGS = ("-fopenmp",)
# Instruction sets the kernels can be built for: `native` (everything this CPU has: 16-lane AVX-512
# micro-kernels where present, else 8-lane AVX2) is what runs; `avx2` keeps AVX-512 off (a second build the
# tests compare with on AVX-512 machines, so the AVX2 micro-kernels are checked there too).
INSTRUCTION_SETS = {"native": (), "avx2": ("-mno-avx512f",)}

_kernels: str | None = None
_module: ModuleType | None = None
_build_error: str | None = None
_lock = threading.Lock()


def check_kernels(name: str) -> str:
    """`name` if it is one of `KERNELS`, else a ValueError naming them (or the new name of an old one)."""
    if name in RENAMED:
        raise ValueError(f"sparse kernels {name!r} are now called {RENAMED[name]!r} (one of {KERNELS})")
    if name not in KERNELS:
        raise ValueError(f"sparse kernels must be one of {KERNELS}, got {name!r}")
    return name


def get_kernels() -> str:
    """The kernels setting: the last `set_kernels`, else `RADARSEG_SPARSE_KERNELS`, else `auto`
    (`RADARSEG_SPARSE_ENGINE`, its earlier name, is refused naming it)."""
    global _kernels
    if _kernels is None:
        settings = environment()
        if settings.sparse_engine is not None:
            raise ValueError(f"{OLD_KERNELS_ENV} is now {KERNELS_ENV} (the sparse kernels: {', '.join(KERNELS)}; "
                             f"the runtime is --runtime torch|torch-int8|onnx|onnx-int8)")
        try:
            _kernels = check_kernels(settings.sparse_kernels)
        except ValueError as error:
            raise ValueError(f"{KERNELS_ENV}: {error}") from None
    return _kernels


def set_kernels(name: str) -> None:
    """Choose the kernels for every later convolution (see the module docstring)."""
    global _kernels
    _kernels = check_kernels(name)


@contextmanager
def using_kernels(name: str) -> Iterator[None]:
    """`set_kernels(name)` inside a `with` block, the previous setting restored after it."""
    previous = get_kernels()
    set_kernels(name)
    try:
        yield
    finally:
        set_kernels(previous)


def cpu_flags() -> str:
    """The CPU's instruction-set flags (Linux `/proc/cpuinfo`), or the processor's name elsewhere."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor() or platform.machine()


@functools.cache
def compiler_identity() -> str:
    """The C++ compiler torch's loader runs (`$CXX`, else `c++`): its path and the first line of `--version`."""
    command = environment().cxx or "c++"
    found = shutil.which(command)
    if found is None:
        return f"{command} (not found)"
    try:
        done = subprocess.run([found, "--version"], capture_output=True, text=True, timeout=30, check=False)
        version = (done.stdout.strip().splitlines() or ["(no version)"])[0]
    except (OSError, subprocess.SubprocessError) as error:
        version = f"(--version failed: {type(error).__name__})"
    return f"{os.path.realpath(found)}: {version}"


def build_environment(instruction_set: str = "native", sources: tuple[Path, ...] = SOURCES) -> dict[str, str]:
    """Everything the code compiled from `sources` for `instruction_set` depends on, by name (`build.json`).

    Raises:
        ValueError: an unknown instruction set.
    """
    if instruction_set not in INSTRUCTION_SETS:
        raise ValueError(f"instruction set must be one of {tuple(INSTRUCTION_SETS)}, got {instruction_set!r}")
    code = hashlib.sha256()
    for source in sources + HEADERS:
        code.update(source.read_bytes())
        code.update(b"\0")
    return {
        "sources": code.hexdigest()[:16],
        # where they are: torch's build.ninja names each source by its path, so one build folder shared by two
        # clones (with one venv, or two) recompiles at every switch between them
        "source_paths": " ".join(str(source) for source in sources),
        "flags": " ".join(CFLAGS + INSTRUCTION_SETS[instruction_set] + LDFLAGS),
        "compiler": compiler_identity(),
        # the interpreter: a venv's own path and prefix, so that two venvs never share (or overwrite) one build
        "interpreter": sys.executable,
        "prefix": sys.prefix,
        "python": sys.version,
        "torch": f"{torch.__version__} at {Path(torch.__file__).parent}",
        "cxx11_abi": str(torch._C._GLIBCXX_USE_CXX11_ABI),
        "cpu": hashlib.sha256(cpu_flags().encode()).hexdigest()[:16],
        "machine": platform.machine(),
    }


def build_key(instruction_set: str = "native", sources: tuple[Path, ...] = SOURCES) -> str:
    """Hash of `build_environment(instruction_set, sources)` (see the module docstring)."""
    text = json.dumps(build_environment(instruction_set, sources), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def build_directory(prefix: str, instruction_set: str = "native", sources: tuple[Path, ...] = SOURCES) -> Path:
    """The folder the extension `prefix` built from `sources` for `instruction_set` in this environment is
    cached in: `build_root() / f"{prefix}_{build_key}"`."""
    return build_root() / f"{prefix}_{build_key(instruction_set, sources)}"


MANIFEST = "build.json"
"""The file in each build folder that says what it was built for (`build_environment`)."""


def build_reason(directory: Path, environment_now: dict[str, str]) -> str:
    """Why the extension in `directory` must be built: no build of that kind yet, an unfinished one, or what
    differs between this environment and the builds of the same extension already cached beside it."""
    if directory.is_dir() and any(directory.iterdir()):
        return "a build in this folder is under way in another process, or did not finish"
    prefix = directory.name.rsplit("_", 1)[0]
    differences = []
    for manifest in sorted(directory.parent.glob(f"{prefix}_*/{MANIFEST}")):
        if manifest.parent.name.rsplit("_", 1)[0] != prefix:
            continue  # another extension whose name starts like this one's
        try:
            cached = json.loads(manifest.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        differences.append(sorted(k for k in environment_now if cached.get(k) != environment_now[k]))
    if not differences:
        return "no build of it is cached yet"
    nearest = min(differences, key=len)
    return (f"{len(differences)} cached build(s) are for other environments; the nearest differs in "
            f"{', '.join(nearest)}")


def build_root() -> Path:
    """Where built extensions are cached."""
    return environment().torch_extensions_dir or Path.home() / ".cache" / "radarseg" / "extensions"


def _ensure_ninja_on_path() -> None:
    """torch's loader runs `ninja` from PATH; a venv used without activation has it beside the interpreter."""
    if shutil.which("ninja"):
        return
    candidates = [Path(sys.executable).parent]
    try:
        import ninja  # noqa: PLC0415

        candidates.insert(0, Path(ninja.BIN_DIR))
    except ImportError:
        pass
    for folder in candidates:
        if (folder / "ninja").is_file():
            os.environ["PATH"] = f"{folder}{os.pathsep}{os.environ.get('PATH', '')}"
            return


def load() -> ModuleType:
    """The compiled kernels, built on first use (minutes at most; seconds when cached).

    Raises:
        RuntimeError: the build failed (no compiler, no ninja, ...); the message says why.
    """
    global _module, _build_error
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        if _build_error is not None:
            raise RuntimeError(_build_error)
        try:
            _module = build("native")
        except RuntimeError as error:
            _build_error = str(error)
            raise
        return _module


@contextmanager
def _build_lock(directory: Path) -> Iterator[None]:
    """Hold an OS file lock on the build directory while torch's loader runs in it. torch's own lock is a file it
    deletes when done, so a build killed halfway (Ctrl-C, a killed test run) leaves it behind and every later
    process waits for it forever; our lock dies with its holder, so whoever holds it may delete a left-over one."""
    with open(directory / ".radarseg-build.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            stale = directory / "lock"  # torch.utils.file_baton's: nobody else can be inside the build now
            if stale.exists():
                logger.warning("removing %s, left by an interrupted build", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build(instruction_set: str) -> ModuleType:
    """The kernels compiled for `instruction_set` (one of `INSTRUCTION_SETS`), from the cache when built before.

    Raises:
        RuntimeError: the build failed; the message says why.
    """
    return build_extension("radarseg_sparse", SOURCES, instruction_set, "the compiled sparse kernels")


def build_extension(prefix: str, sources: tuple[Path, ...], instruction_set: str, what: str) -> ModuleType:
    """`sources` compiled as one extension for `instruction_set` (one of `INSTRUCTION_SETS`), cached in
    `build_root() / f"{prefix}_{build_key}"`; `what` names the kernels in the log and in the error.

    Raises:
        ValueError: an unknown instruction set.
        RuntimeError: the build failed; the message says why.
    """
    from torch.utils import cpp_extension  # noqa: PLC0415  (imports setuptools: only when needed)

    environment_now = build_environment(instruction_set, sources)
    directory = build_directory(prefix, instruction_set, sources)
    name = directory.name
    cached = (directory / f"{name}.so").is_file()
    if not cached:  # a warning: minutes of compiling should never pass without a word, whatever the log level
        logger.warning("building %s (%s) in %s, because %s (minutes; cached afterwards)", what, instruction_set,
                       directory, build_reason(directory, environment_now))
    started = time.perf_counter()
    try:
        _ensure_ninja_on_path()
        directory.mkdir(parents=True, exist_ok=True)
        with _build_lock(directory):
            module = cpp_extension.load(
                name=name, sources=[str(source) for source in sources], build_directory=str(directory),
                extra_cflags=list(CFLAGS + INSTRUCTION_SETS[instruction_set]), extra_ldflags=list(LDFLAGS),
                verbose=False,
            )
    except Exception as error:  # noqa: BLE001  (compiler, ninja, linker or file errors all mean "no kernels")
        first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise RuntimeError(f"{what} did not build ({type(error).__name__}: {first_line})") from error
    if not cached:
        (directory / MANIFEST).write_text(json.dumps(environment_now, indent=2, sort_keys=True) + "\n")
        logger.warning("built %s in %.1f s", what, time.perf_counter() - started)
    return module


def available() -> bool:
    """Whether the compiled kernels load (building them if needed); never raises."""
    try:
        load()
    except RuntimeError:
        return False
    return True


_warned = False


def use_compiled(*tensors: Tensor) -> bool:
    """Whether the compiled engine runs a convolution on these tensors under the current setting.

    Raises:
        RuntimeError: the setting is `compiled` and the kernels did not build.
    """
    if not all(t.dtype == torch.float32 for t in tensors):
        return False
    return enabled_on(*(t.device for t in tensors))


def enabled_on(*devices: torch.device) -> bool:
    """Whether the compiled engine runs work on these devices under the current setting (CPU only; under `auto`
    a failed build warns once and answers False).

    Raises:
        RuntimeError: the setting is `compiled` and the kernels did not build.
    """
    global _warned
    engine = get_kernels()
    if engine == "reference" or not all(device.type == "cpu" for device in devices):
        return False
    if engine == "compiled":
        load()
        return True
    try:
        load()
    except RuntimeError as error:
        if not _warned:
            _warned = True
            warnings.warn(f"{error}; using the pure-PyTorch sparse kernels", RuntimeWarning, stacklevel=3)
        return False
    return True


def neighbour_conv(src: Tensor, neighbours: Tensor, weight: Tensor) -> Tensor:
    """`out[j] = sum_k src[neighbours[j, k]] @ weight[k]`, missing neighbours (= len(src)) skipped.

    Args:
        src: (N, C) float32.
        neighbours: (M, K) int64 rows of `src`, N where missing.
        weight: (K, C, D).

    Returns:
        (M, D).
    """
    return load().neighbour_conv(src.contiguous(), neighbours.contiguous(), weight.contiguous())


def scatter_conv(src: Tensor, neighbours: Tensor, weight: Tensor, num_out: int) -> Tensor:
    """`out[neighbours[j, k]] = src[j] @ weight[k]` where present; each output row must be reached at most
    once (a down-sampling map read backwards), rows never reached are zero.

    Args:
        src: (M, C) float32.
        neighbours: (M, K) int64 output rows, `num_out` where missing.
        weight: (K, C, D).
        num_out: output rows.

    Returns:
        (num_out, D).
    """
    return load().scatter_conv(src.contiguous(), neighbours.contiguous(), weight.contiguous(), num_out)


def neighbour_weight_grad(src: Tensor, neighbours: Tensor, dense: Tensor) -> Tensor:
    """`grad[k] = sum_j src[neighbours[j, k]]^T dense[j]` over present neighbours.

    Args:
        src: (N, A) float32.
        neighbours: (M, K) int64 rows of `src`, N where missing.
        dense: (M, B).

    Returns:
        (K, A, B).
    """
    return load().neighbour_weight_grad(src.contiguous(), neighbours.contiguous(), dense.contiguous())


def grid_neighbours(grid: Tensor, flat: Tensor, delta: Tensor) -> Tensor:
    """`out[j, k] = grid[flat[j] + delta[k]]` as int64: a kernel map's neighbour table read from a dense index grid
    in one pass (`models.sparse.kernel_map.VoxelIndex`).

    Args:
        grid: (cells,) int32 row of each cell.
        flat: (M,) int64 cell of each output.
        delta: (K,) int64 cell offset of each kernel offset; every `flat[j] + delta[k]` must lie in the grid.

    Returns:
        (M, K) int64.
    """
    return load().grid_neighbours(grid.contiguous(), flat.contiguous(), delta.contiguous())


def neighbour_conv_fused(src: Tensor, neighbours: Tensor, weight: Tensor, bias: Tensor | None = None,
                         residual: Tensor | None = None, relu: bool = False) -> Tensor:
    """:func:`neighbour_conv` with its inference epilogue: `max(out + bias + residual, 0)` written with the rows
    (each part optional: `bias` (D,), `residual` (M, D), `relu`). No autograd."""
    return load().neighbour_conv_fused(src.contiguous(), neighbours.contiguous(), weight.contiguous(),
                                       None if bias is None else bias.contiguous(),
                                       None if residual is None else residual.contiguous(), relu)


def scatter_conv_fused(src: Tensor, neighbours: Tensor, weight: Tensor, num_out: int, bias: Tensor | None = None,
                       relu: bool = False) -> Tensor:
    """:func:`scatter_conv` with its inference epilogue `max(out + bias, 0)` (rows never reached: `max(bias, 0)`).
    No autograd."""
    return load().scatter_conv_fused(src.contiguous(), neighbours.contiguous(), weight.contiguous(), num_out,
                                     None if bias is None else bias.contiguous(), relu)


def pyramid_maps(coords: Tensor, levels: int, max_cells: int) -> list[Tensor] | None:
    """Every level's coordinates, 3^3 submanifold map and 2^3 down-sampling map of a voxel pyramid in one pass
    (`csrc/kernel_maps.cpp`; tables equal to `models.sparse.kernel_map.build_kernel_map`'s).

    Args:
        coords: (N, 4) int64 `(batch, x, y, z)` of level 0, sorted by key and unique.
        levels: tensor strides 1, 2, ..., 2^(levels - 1).
        max_cells: largest (batch, x, y) column index of a level.

    Returns:
        Five tensors per level (coords, 3^3 table, its pair counts, 2^3 table to the next level, its pair counts;
        the last level's 2^3 table has no rows), or None where `coords` are not sorted and unique, are empty, or a
        level's column index would exceed `max_cells`.
    """
    out = load().pyramid_maps(coords.contiguous(), levels, max_cells)
    return out or None
