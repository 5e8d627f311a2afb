"""One runner for every benchmark, and the history their figures accumulate in.

    .venv/bin/python -m benchmarks list                  # every benchmark by name, and what it needs
    .venv/bin/python -m benchmarks run simulate           # one, by name (arguments after the name go to it)
    .venv/bin/python -m benchmarks run --all              # every one that runs on the repository alone (make bench)

Each benchmark is a module of this folder that still runs by itself (``python -m benchmarks.simulate``) and writes
its figures to ``benchmarks/results/NAME.json`` (the latest run on this checkout). The runner runs it in a fresh
process and appends one line to ``benchmarks/results/history/NAME.jsonl`` holding what it wrote, the machine (CPU
model and instruction-set flags, cores), the load average before and after, the commit (and whether the tree had
uncommitted changes), the date and the arguments: runs on other machines and commits add lines instead of
replacing each other's figures, in the spirit of asv and pytest-benchmark. One-off studies live in
``experiments/studies/``, not here.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

BENCHMARKS_DIR = Path(__file__).resolve().parent
REPO = BENCHMARKS_DIR.parent
RESULTS = BENCHMARKS_DIR / "results"
HISTORY = RESULTS / "history"
HELPERS = ("__main__", "harness", "timing")  # modules of this folder that are not benchmarks
FLAG_PREFIXES = ("sse4", "avx", "fma", "amx", "f16c", "bmi2", "asimd", "sve", "neon")  # what the kernels can use


@dataclass(frozen=True)
class Benchmark:
    """A benchmark by module name; ``needs``: what it needs beyond the repository (run it by name with that;
    ``run --all`` passes over it saying so)."""

    name: str
    needs: str = ""


REGISTRY: tuple[Benchmark, ...] = (
    Benchmark("simulate"), Benchmark("detector"), Benchmark("stage1"), Benchmark("sparse_conv"),
    Benchmark("end_to_end"), Benchmark("preprocess"), Benchmark("service"), Benchmark("scale"),
    Benchmark("baselines"), Benchmark("compare"), Benchmark("export"), Benchmark("region_growing"),
    Benchmark("tracking"), Benchmark("fused_segmenter"), Benchmark("kernel_maps"), Benchmark("frame_profile"),
    Benchmark("segmenter_train"), Benchmark("streams"), Benchmark("recording_export"), Benchmark("open_inference"),
    Benchmark("nxp_scale"), Benchmark("int8_engine"), Benchmark("int8_start"), Benchmark("detector_crops"),
    Benchmark("roi_samples", needs="--store STORE: a store of the radar whose ROI samples are timed"),
    Benchmark("edge", needs="--store STORE --calibration STORE: a fresh evaluation store and a calibration store"),
    Benchmark("onnx_profile", needs="--store STORE: the store whose frames are timed"),
    Benchmark("learning_curves", needs="training runs with curve.jsonl (LABEL=RUN_DIR ...)"),
)
BY_NAME = {benchmark.name: benchmark for benchmark in REGISTRY}

SHIPPED_PAIRS = {"small": (REPO / "checkpoints" / "detector.pt", REPO / "checkpoints" / "segmenter.pt"),
                 "carrada": (REPO / "checkpoints" / "carrada" / "detector.pt",
                             REPO / "checkpoints" / "carrada" / "segmenter.pt")}
"""The shipped detector and segmenter of each preset that has a pair: what the benchmarks run by default."""


def benchmark_modules() -> list[str]:
    """The module names of this folder that are benchmarks (every one must be registered)."""
    return sorted(p.stem for p in BENCHMARKS_DIR.glob("*.py") if p.stem not in HELPERS)


def machine() -> dict[str, Any]:
    """The CPU model, its vector instruction-set flags, the cores (all, and usable by this process), the OS."""
    model, flags = platform.processor() or platform.machine(), []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("", platform.machine(), platform.processor()):
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = sorted(f for f in value.split() if f.startswith(FLAG_PREFIXES))
    except OSError:  # not Linux: the platform's name alone
        pass
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": model, "flags": flags, "cores": os.cpu_count(), "usable_cores": usable,
            "system": f"{platform.system()} {platform.release()}", "python": platform.python_version()}


def commit() -> dict[str, Any]:
    """The checkout's commit and whether tracked files differ from it (None outside a git checkout)."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()

    try:
        return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None}


def _snapshot(results: Path) -> dict[Path, int]:
    return {path: path.stat().st_mtime_ns for path in results.glob("*.json")}


@dataclass(frozen=True)
class Table:
    """A fixed-width text table the benchmarks print: ``columns`` of (title, format spec of the values), joined by
    ``separator``. A column whose spec is a bare width (``"8"``) holds text, title left-aligned like its values;
    a spec with an alignment (``"<28"``, ``">7"``) aligns the title the same way; any other spec (``"8.3f"``,
    ``"6.1%"``) holds numbers under a right-aligned title."""

    columns: tuple[tuple[str, str], ...]
    separator: str = " "

    def header(self) -> str:
        return self.separator.join(format(title, _title_spec(spec)) for title, spec in self.columns)

    def row(self, *values: object) -> str:
        if len(values) != len(self.columns):
            raise ValueError(f"a row of {len(self.columns)} values expected, got {len(values)}")
        return self.separator.join(format(value, spec) for value, (_, spec) in zip(values, self.columns, strict=True))


def _title_spec(spec: str) -> str:
    align, width, rest = re.fullmatch(r"([<>^]?)(\d*)(.*)", spec).groups()
    return (align or ("<" if not rest else ">")) + width


def write_results(path: Path, result: dict) -> None:
    """``result`` as indented JSON at ``path`` (its folder made if missing)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2))


def write_with_load(results: dict, out: str | Path) -> None:
    """``results`` with the load average after the run (``load_average_after``) written to ``out``, and where."""
    results["load_average_after"] = os.getloadavg()
    write_results(Path(out), results)
    print(f"wrote {out}")


def print_json(result: dict) -> None:
    """The figures as indented JSON on stdout: the report of a benchmark without a table of its own."""
    print(json.dumps(result, indent=2))


def print_load(result: dict) -> None:
    """The line ending a one-thread comparison: the load average before and after, and its ``cpu`` entry."""
    print(f"load average {result['load_average_before']} -> {result['load_average_after']}; {result['cpu']}")


def int_options_main(results: Path, run: Callable[..., dict], doc: str | None, argv: list[str] | None, *,
                     report: Callable[[dict], None] = print_json, positive: tuple[str, ...] = (),
                     **defaults: int) -> int:
    """A benchmark's command line: an integer option ``--NAME`` per keyword of ``run`` (``defaults``: their
    defaults; ``positive``: those that must be >= 1) and ``--out`` (default ``results``); ``run``'s figures written
    there as JSON, then given to ``report`` (default: printed as JSON). ``doc``: the module's docstring."""
    parser = argparse.ArgumentParser(description=(doc or "").strip().splitlines()[0] if doc else None)
    for name, default in defaults.items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=int, default=default)
    parser.add_argument("--out", type=Path, default=results, help=f"figures file (default: {results})")
    options = vars(parser.parse_args(argv))
    out = options.pop("out")
    too_small = [f"--{name.replace('_', '-')}" for name in positive if options[name] < 1]
    if too_small:
        parser.error(f"{' and '.join(too_small)} must be >= 1")
    result = run(**options)
    write_results(out, result)
    report(result)
    return 0


def run(name: str, argv: list[str]) -> int:
    """Run benchmark ``name`` with ``argv`` in a fresh process; on success, append its record to the history.
    Returns the benchmark's exit code."""
    if name not in BY_NAME:
        raise SystemExit(f"unknown benchmark {name!r}; the benchmarks: {', '.join(BY_NAME)}")
    return recorded(name, [sys.executable, "-m", f"benchmarks.{name}", *argv], argv)


def recorded(name: str, command: list[str], argv: list[str], *, results: Path = RESULTS,
             history: Path = HISTORY) -> int:
    """Run ``command`` (benchmark ``name`` given ``argv``) from the repository; when it succeeds, append to
    ``history/NAME.jsonl`` one record of the JSON files it wrote into ``results`` and of the run."""
    before, load_before, started = _snapshot(results), os.getloadavg(), time.perf_counter()
    date = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    code = subprocess.run(command, cwd=REPO).returncode
    if code != 0:
        return code
    written = {path.name: json.loads(path.read_text()) for path, mtime in _snapshot(results).items()
               if before.get(path) != mtime}
    record = {"benchmark": name, "argv": argv, "date": date, **commit(), "machine": machine(),
              "load_average_before": load_before, "load_average_after": os.getloadavg(),
              "wall_s": round(time.perf_counter() - started, 3), "results": written}
    history.mkdir(parents=True, exist_ok=True)
    with (history / f"{name}.jsonl").open("a") as out:
        out.write(json.dumps(record, separators=(",", ":")) + "\n")
    print(f"{name}: {', '.join(written) or 'no results file written'} -> {history / f'{name}.jsonl'}")
    return 0


def run_all() -> int:
    """Every registered benchmark that needs nothing beyond the repository, in registry order; the first failure
    stops the run (its exit code returned)."""
    for benchmark in REGISTRY:
        if benchmark.needs:
            print(f"== {benchmark.name}: passed over (needs {benchmark.needs}; run it by name)")
            continue
        print(f"== {benchmark.name}", flush=True)
        code = run(benchmark.name, [])
        if code:
            return code
    return 0


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["list"]:
        for benchmark in REGISTRY:
            print(f"{benchmark.name:18s} {'needs ' + benchmark.needs if benchmark.needs else ''}".rstrip())
        return 0
    if args[:2] == ["run", "--all"]:
        return run_all()
    if args[:1] == ["run"] and len(args) >= 2:
        return run(args[1], args[2:])
    print(__doc__.split("\n\n")[1], file=sys.stderr)
    return 2
