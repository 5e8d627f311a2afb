"""The start of an int8 model: the shipped pair loaded float, then int8 twice into a calibration cache of its own.

    .venv/bin/python -m benchmarks.int8_start

The first int8 load calibrates (simulated frames of the preset through the float pipeline,
``models.quantized.erasenet``) and keeps the calibration (``models.quantized.calibration_cache``); the second reads
it back. Figures, one thread, each a single load in this process (the detector's tracing is in every one): seconds
of the float load, of the first and second int8 loads, and of reading the kept calibration alone (its key: both
checkpoints' sha256 and the source's; the file; the int8 network built from it). Writes
benchmarks/results/int8_start.json with the CPU's flags and the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

from benchmarks.harness import machine, print_json, write_with_load

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "int8_start.json"


def timed(load):  # noqa: ANN001, ANN201
    started = time.perf_counter()
    value = load()
    return value, time.perf_counter() - started


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--detector", default=str(ROOT / "checkpoints" / "detector.pt"))
    parser.add_argument("--segmenter", default=str(ROOT / "checkpoints" / "segmenter.pt"))
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    results: dict = {"machine": machine(), "load_average_before": os.getloadavg(), "threads": 1,
                     "pair": [args.detector, args.segmenter]}
    with tempfile.TemporaryDirectory(prefix="int8-start-") as scratch:
        os.environ["RADARSEG_INT8_CACHE"] = scratch  # read by models.environment when the cache is looked up
        from models.checkpoint import load_pair
        from models.quantized import calibration_cache
        from models.quantized.erasenet import calibration_key
        from models.runtime import load_erasenet

        _, results["float_load_seconds"] = timed(lambda: load_erasenet(args.detector, args.segmenter))
        _, results["int8_first_load_seconds"] = timed(
            lambda: load_erasenet(args.detector, args.segmenter, runtime="torch-int8"))
        net, results["int8_second_load_seconds"] = timed(
            lambda: load_erasenet(args.detector, args.segmenter, runtime="torch-int8"))
        detector, segmenter = load_pair(args.detector, args.segmenter)
        calibration_cache.source_digest.cache_clear()  # as a fresh process computes it

        def read_back():  # noqa: ANN202
            key = calibration_key(net, detector, segmenter)
            return calibration_cache.load(calibration_cache.cache_path(key), key, net.segmenter_form.fused)

        (int8, problem), results["calibration_read_seconds"] = timed(read_back)
        assert int8 is not None, problem
        results["kept_files"] = [p.name for p in Path(scratch).glob("*.json")]
        results["preset"] = net.profile.name
    write_with_load(results, args.out)
    print_json({k: v for k, v in results.items() if k != "machine"})
    return results


if __name__ == "__main__":
    sys.exit(0 if main() else 1)
