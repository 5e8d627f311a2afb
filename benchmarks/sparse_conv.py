"""Benchmark of the sparse convolution's two engines (compiled `native`, pure-PyTorch `torch`) against dense
Conv3d, and a MinkUNet training step.

Measured side by side in one run, the engines interleaved (`KERNEL_KEYS`):
- a 3^3 submanifold conv 32 -> 32, forward + backward, at 20k and 100k voxels filling about 5% of their
  bounding grid, next to a dense `nn.Conv3d` on that bounding grid (the compiled engine also timed alone, after the
  interleaved rounds: `dense_over_native_alone`); two layouts: solid blobs like
  region-grown ROIs (about 21 neighbours per voxel) and uniformly random voxels (about 2);
- a MinkUNet (ratio 0.37, 4 features, 5 classes) SGD training step at 5k and 20k voxels, kernel maps
  built inside the step as in training;
- the engine's paths side by side on ROI-like blobs (`paths`): a 3^3 map built through the dense index
  grid and through hashing, and a 3^3 submanifold conv forward + backward at 8-64 channels on the
  torch engine's per-offset path, its GEMM path and the one `choose_path` picks, and on the native
  engine; and, when spconv happens to be importable (not a dependency), its CPU forward on the same voxels.

The machine's CPU model, SIMD flags and load average are recorded with the figures (ratios between the
engines and against dense are what carry over between machines, not the times).

Prints the figures and writes them to `benchmarks/results/sparse_conv.json`. Never asserts a time.

    python -m benchmarks.sparse_conv [--device cpu|cuda] [--threads 1] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from models.segmenter.minkunet import MinkUNet
from models.sparse import (
    SparseTensor,
    SubmanifoldConv3d,
    VoxelIndex,
    build_kernel_map,
    choose_path,
    compiled,
    last_forward_macs,
)

RESULTS = Path(__file__).parent / "results" / "sparse_conv.json"
KERNEL_KEYS = ("native", "torch")  # the keys of the results: the compiled and the reference sparse engine
SPARSE_ENGINE = {"native": "compiled", "torch": "reference"}  # models.sparse.compiled's names
SIMD_FLAGS = ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512_vnni", "amx_tile", "asimd", "sve")


def machine_info() -> dict:
    """CPU model, SIMD flags, cores, torch threads and load: what every figure is recorded with."""
    flags = set(compiled.cpu_flags().split())
    model = next((line.split(":", 1)[1].strip() for line in _cpuinfo_lines() if line.startswith("model name")),
                 platform.processor())
    return {"cpu": model, "simd_flags": [f for f in SIMD_FLAGS if f in flags], "cpus": os.cpu_count(),
            "torch": torch.__version__, "threads": torch.get_num_threads(), "load_average": os.getloadavg()}


def _cpuinfo_lines() -> list[str]:
    try:
        return Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return []


def engine_build() -> dict:
    """Whether the native engine loads, and the seconds its load took (a first build, or the cache)."""
    started = time.perf_counter()
    ok = compiled.available()
    return {"native_available": ok, "load_s": time.perf_counter() - started}


@dataclass(frozen=True)
class BenchConfig:
    """What to measure. `smoke` shrinks everything so the script runs in seconds."""

    device: str = "cpu"
    conv_voxels: tuple[int, ...] = (20_000, 100_000)
    layouts: tuple[str, ...] = ("blobs", "uniform")  # solid ROI-like blobs; uniform random voxels
    step_voxels: tuple[int, ...] = (5_000, 20_000)
    path_voxels: int = 20_000
    path_channels: tuple[int, ...] = (8, 16, 32, 64)
    density: float = 0.05
    repeats: int = 7
    dense_repeats: int = 2
    seed: int = 0
    threads: int = 1
    output: str = str(RESULTS)


def clustered_voxels(num_voxels: int, density: float, generator: torch.Generator) -> Tensor:
    """Unique voxels (num_voxels, 4), batch 0, filling about `density` of their bounding box.

    Blobs leave the corners of the box empty, so the grid is enlarged until the measured density is
    within 20% of the target (at most 4 tries).
    """
    side = (num_voxels / density) ** (1 / 3)
    for _ in range(4):
        coords = _blobs(num_voxels, round(side), generator)
        measured = num_voxels / float((coords[:, 1:].max(dim=0).values + 1).prod())
        if measured < 1.2 * density:
            break
        side *= (measured / density) ** (1 / 3)
    return coords


def _blobs(num_voxels: int, side: int, generator: torch.Generator) -> Tensor:
    """Unique voxels (num_voxels, 4), batch 0: solid ellipsoids (like region-grown ROIs, radii 2-8
    voxels) scattered over a cubic grid of `side` voxels.

    Returns coordinates shifted so the bounding box starts at 0.
    """
    span = torch.arange(-8, 9)
    box = torch.stack(torch.meshgrid(span, span, span, indexing="ij"), dim=-1).reshape(-1, 3)
    found = torch.empty(0, 3, dtype=torch.int64)
    while len(found) < num_voxels:  # blobs may overlap: count unique voxels after each batch of blobs
        blobs, total = [found], len(found)
        while total < num_voxels:
            centre = (torch.rand(3, generator=generator) * (side - 16)).long() + 8
            radii = 2.0 + 6.0 * torch.rand(3, generator=generator)
            blobs.append(box[((box / radii) ** 2).sum(dim=1) <= 1] + centre)
            total += len(blobs[-1])
        found = torch.unique(torch.cat(blobs), dim=0)
    keep = torch.randperm(len(found), generator=generator)[:num_voxels]
    spatial = found[keep]
    spatial -= spatial.min(dim=0).values
    return torch.cat([torch.zeros(num_voxels, 1, dtype=torch.int64), spatial], dim=1)


def timed(fn: Callable[[], object], repeats: int, device: torch.device) -> list[float]:
    """Wall seconds of `repeats` calls after one warm-up call."""

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fn()
    sync()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - start)
    return times


def interleaved(fn: Callable[[], object], repeats: int, device: torch.device) -> dict[str, list[float]]:
    """Wall seconds of `repeats` calls per engine, the engines taking turns (one warm-up call each)."""
    times: dict[str, list[float]] = {engine: [] for engine in KERNEL_KEYS}
    for repeat in range(repeats + 1):
        for engine in KERNEL_KEYS:
            with compiled.using_kernels(SPARSE_ENGINE[engine]):
                start = time.perf_counter()
                fn()
                if device.type == "cuda":
                    torch.cuda.synchronize(device)
                if repeat:  # the first call of each engine warms it up
                    times[engine].append(time.perf_counter() - start)
    return times


def uniform_voxels(num_voxels: int, density: float, generator: torch.Generator) -> Tensor:
    """Unique voxels (num_voxels, 4), batch 0, drawn uniformly from a cube they fill to `density`
    (few neighbours per voxel: the easy case for sparse convolution)."""
    side = round((num_voxels / density) ** (1 / 3))
    flat = torch.randperm(side**3, generator=generator)[:num_voxels]
    spatial = torch.stack([flat // side**2, (flat // side) % side, flat % side], dim=1)
    return torch.cat([torch.zeros(num_voxels, 1, dtype=torch.int64), spatial], dim=1)


LAYOUTS = {"blobs": clustered_voxels, "uniform": uniform_voxels}


def bench_submanifold_vs_dense(num_voxels: int, layout: str, cfg: BenchConfig, device: torch.device) -> dict:
    """One 3^3 conv 32 -> 32, forward + backward, sparse (map cached, map build apart) and dense."""
    generator = torch.Generator().manual_seed(cfg.seed)
    coords = LAYOUTS[layout](num_voxels, cfg.density, generator).to(device)
    grid_shape = [int(v) + 1 for v in coords[:, 1:].max(dim=0).values]
    feats = torch.randn(num_voxels, 32, generator=generator).to(device).requires_grad_(True)
    conv = SubmanifoldConv3d(32, 32).to(device)
    x = SparseTensor(coords, feats)

    build_times = timed(lambda: SparseTensor(coords, feats).cache.kernel_map(1, 3, 1), cfg.repeats, device)
    kernel_map = x.cache.kernel_map(1, 3, 1)

    def sparse_step() -> None:
        conv(x).feats.sum().backward()

    sparse_times = interleaved(sparse_step, cfg.repeats, device)
    with compiled.using_kernels(SPARSE_ENGINE["native"]):  # the compiled engine alone, no other engine's runs between
        native_alone = timed(sparse_step, cfg.repeats, device)

    dense_conv = nn.Conv3d(32, 32, 3, padding=1, bias=False).to(device)
    dense_input = torch.randn(1, 32, *grid_shape, generator=generator).to(device).requires_grad_(True)

    def dense_step() -> None:
        dense_conv(dense_input).sum().backward()

    dense_times = timed(dense_step, cfg.dense_repeats, device)
    grid_cells = grid_shape[0] * grid_shape[1] * grid_shape[2]
    dense_s = statistics.median(dense_times)
    sparse_s = {engine: statistics.median(times) for engine, times in sparse_times.items()}
    return {
        "voxels": num_voxels,
        "layout": layout,
        "bounding_grid": grid_shape,
        "density": num_voxels / grid_cells,
        "pairs_per_voxel": kernel_map.num_pairs / num_voxels,
        "sparse_macs_forward": conv.last_macs,
        "dense_macs_forward": grid_cells * 27 * 32 * 32,
        "kernel_map_build_s": statistics.median(build_times),
        "sparse_fwd_bwd_s": sparse_s,
        "sparse_fwd_bwd_min_s": {engine: min(times) for engine, times in sparse_times.items()},
        "dense_fwd_bwd_s": dense_s,
        "dense_fwd_bwd_min_s": min(dense_times),
        "dense_over_sparse": {engine: dense_s / t for engine, t in sparse_s.items()},
        "native_alone_fwd_bwd_s": statistics.median(native_alone),
        "dense_over_native_alone": dense_s / statistics.median(native_alone),
        "torch_over_native": sparse_s["torch"] / sparse_s["native"],
    }


def bench_minkunet_step(num_voxels: int, cfg: BenchConfig, device: torch.device) -> dict:
    """One SGD step of MinkUNet ratio 0.37 on one sample of `num_voxels` voxels (maps built in the step)."""
    generator = torch.Generator().manual_seed(cfg.seed + 1)
    coords = clustered_voxels(num_voxels, cfg.density, generator).to(device)
    feats = torch.randn(num_voxels, 4, generator=generator).to(device)
    labels = torch.randint(0, 5, (num_voxels,), generator=generator).to(device)
    model = MinkUNet.from_ratio(0.37, in_channels=4, num_classes=5).to(device)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.24, momentum=0.9)

    def step() -> None:
        optimizer.zero_grad(set_to_none=True)
        loss = nn.functional.cross_entropy(model(SparseTensor(coords, feats)), labels)
        loss.backward()
        optimizer.step()

    times = interleaved(step, cfg.repeats, device)
    medians = {engine: statistics.median(t) for engine, t in times.items()}
    return {
        "voxels": num_voxels,
        "params": sum(p.numel() for p in model.parameters()),
        "forward_macs": last_forward_macs(model),
        "train_step_s": medians,
        "train_step_min_s": {engine: min(t) for engine, t in times.items()},
        "torch_over_native": medians["torch"] / medians["native"],
    }


def bench_paths(cfg: BenchConfig, device: torch.device) -> dict:
    """Map building (grid, hashing) and a 3^3 conv C -> C, forward + backward, per path, interleaved."""
    generator = torch.Generator().manual_seed(cfg.seed + 2)
    coords = clustered_voxels(cfg.path_voxels, cfg.density, generator).to(device)
    out = {"voxels": cfg.path_voxels}
    map_times = {"grid": [], "hashing": []}
    for _ in range(cfg.repeats):
        for name, max_cells in (("grid", None), ("hashing", 0)):
            start = time.perf_counter()
            index = VoxelIndex(coords) if max_cells is None else VoxelIndex(coords, max_cells=max_cells)
            build_kernel_map(index, coords, 3, 1, same_coords=True)
            map_times[name].append(time.perf_counter() - start)
    out["map_build_s"] = {name: statistics.median(t) for name, t in map_times.items()}
    kernel_map = SparseTensor(coords, torch.zeros(len(coords), 1, device=device)).cache.kernel_map(1, 3, 1)
    out["fill"] = kernel_map.num_pairs / (kernel_map.num_out * kernel_map.num_offsets)
    rows = []
    for channels in cfg.path_channels:
        feats = torch.randn(len(coords), channels, generator=generator).to(device).requires_grad_(True)
        conv = SubmanifoldConv3d(channels, channels).to(device)
        x = SparseTensor(coords, feats)
        times = {"per_offset": [], "gemm": [], "native": []}
        for _ in range(cfg.repeats):
            for path in times:
                conv.path = "auto" if path == "native" else path
                with compiled.using_kernels("compiled" if path == "native" else "reference"):
                    start = time.perf_counter()
                    conv(x).feats.sum().backward()
                    times[path].append(time.perf_counter() - start)
        conv.path = "auto"
        row = {"channels": channels, "chosen": choose_path(kernel_map, channels, channels, transposed=False),
               "useful_macs": conv.last_macs, **{f"{p}_fwd_bwd_s": statistics.median(t) for p, t in times.items()}}
        row["gemm_over_per_offset"] = row["gemm_fwd_bwd_s"] / row["per_offset_fwd_bwd_s"]
        best_torch = min(row["gemm_fwd_bwd_s"], row["per_offset_fwd_bwd_s"])
        row["best_torch_path_over_native"] = best_torch / row["native_fwd_bwd_s"]
        row["native_gmacs_per_s"] = 3 * row["useful_macs"] / row["native_fwd_bwd_s"] / 1e9  # fwd + 2 bwd products
        row["spconv_fwd_s"] = spconv_forward(coords, channels, cfg.repeats)
        rows.append(row)
    out["submanifold_fwd_bwd"] = rows
    return out


def spconv_forward(coords: Tensor, channels: int, repeats: int) -> float | None:
    """spconv's CPU forward of a 3^3 submanifold conv on the same voxels (index build included), or None
    when spconv is not importable (it is not a dependency)."""
    try:
        import spconv.pytorch as spconv  # noqa: PLC0415
    except ImportError:
        return None
    spatial = coords[:, 1:].max(dim=0).values + 1
    conv = spconv.SubMConv3d(channels, channels, 3, bias=False, indice_key="bench")
    feats = torch.randn(len(coords), channels)
    indices = coords.int().cpu()
    times = []
    with torch.no_grad():
        for _ in range(repeats + 1):
            start = time.perf_counter()
            conv(spconv.SparseConvTensor(feats, indices, spatial.tolist(), 1))
            times.append(time.perf_counter() - start)
    return statistics.median(times[1:])


def main(cfg: BenchConfig) -> dict:
    """Run every measurement, write the JSON file, return the results."""
    device = torch.device(cfg.device)
    torch.set_num_threads(cfg.threads)
    build = engine_build()  # before the machine's figures: a first build loads the machine for a minute
    machine = machine_info()
    machine["load_average_before"] = machine.pop("load_average")
    if device.type == "cuda":
        machine["device"] = torch.cuda.get_device_name(device)
    results = {
        "config": asdict(cfg),
        "machine": machine,
        "engine_build": build,
        "submanifold_conv_32_32": [
            bench_submanifold_vs_dense(n, layout, cfg, device) for layout in cfg.layouts for n in cfg.conv_voxels
        ],
        "minkunet_r037_train_step": [bench_minkunet_step(n, cfg, device) for n in cfg.step_voxels],
        "paths": bench_paths(cfg, device),
    }
    results["machine"]["load_average_after"] = os.getloadavg()
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(results, indent=2) + "\n")
    return results


def parse_args(argv: list[str] | None = None) -> BenchConfig:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, runs in seconds")
    parser.add_argument("--output", default=str(RESULTS), help="JSON file to write")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = parser.parse_args(argv)
    if args.smoke:
        return BenchConfig(
            device=args.device, conv_voxels=(2_000,), step_voxels=(1_000,), repeats=1, dense_repeats=1,
            path_voxels=2_000, path_channels=(8,), output=args.output, threads=args.threads,
        )  # fmt: skip
    return BenchConfig(device=args.device, output=args.output, threads=args.threads)


def _print_paths(paths: dict) -> None:
    maps = paths["map_build_s"]
    print(f"engine paths on {paths['voxels']} blob voxels (fill {paths['fill']:.2f}): 3^3 map grid "
          f"{maps['grid'] * 1e3:.1f} ms, hashing {maps['hashing'] * 1e3:.1f} ms")
    for row in paths["submanifold_fwd_bwd"]:
        spconv_ms = "n/a" if row["spconv_fwd_s"] is None else f"{row['spconv_fwd_s'] * 1e3:.1f} ms"
        print(f"  {row['channels']:3} ch fwd+bwd: torch per_offset {row['per_offset_fwd_bwd_s'] * 1e3:7.1f} ms, gemm "
              f"{row['gemm_fwd_bwd_s'] * 1e3:7.1f} ms (x{row['gemm_over_per_offset']:.2f}), chosen {row['chosen']}; "
              f"native {row['native_fwd_bwd_s'] * 1e3:7.1f} ms ({row['best_torch_path_over_native']:.2f}x the best "
              f"torch path, {row['native_gmacs_per_s']:.1f} GMAC/s); spconv fwd {spconv_ms}")


def report(results: dict) -> None:
    """Print the figures as two small tables."""
    print(f"machine: {results['machine']}")
    print(f"native engine: {results['engine_build']}")
    print("submanifold 3^3 conv 32->32, forward+backward (median s; dense/sparse per engine)")
    print(f"{'layout':>8} {'voxels':>8} {'grid':>16} {'density':>8} {'pairs/vox':>9} {'map s':>8} "
          f"{'native s':>9} {'torch s':>9} {'dense s':>9} {'dense/native':>12} {'dense/torch':>11} "
          f"{'native alone':>12}")  # fmt: skip
    for row in results["submanifold_conv_32_32"]:
        grid = "x".join(str(v) for v in row["bounding_grid"])
        sparse, ratio = row["sparse_fwd_bwd_s"], row["dense_over_sparse"]
        print(
            f"{row['layout']:>8} {row['voxels']:>8} {grid:>16} {row['density']:>8.3f} {row['pairs_per_voxel']:>9.2f} "
            f"{row['kernel_map_build_s']:>8.4f} {sparse['native']:>9.4f} {sparse['torch']:>9.4f} "
            f"{row['dense_fwd_bwd_s']:>9.3f} {ratio['native']:>12.1f} {ratio['torch']:>11.1f} "
            f"{row['dense_over_native_alone']:>12.1f}"
        )
    _print_paths(results["paths"])
    print("MinkUNet ratio 0.37 training step (SGD, maps built in the step)")
    for row in results["minkunet_r037_train_step"]:
        step = row["train_step_s"]
        print(
            f"{row['voxels']:>8} voxels: native {step['native']:.3f} s, torch {step['torch']:.3f} s median "
            f"({row['torch_over_native']:.2f}x), {row['params']:,} params, "
            f"{row['forward_macs'] / 1e9:.3f} GMACs forward"
        )


if __name__ == "__main__":
    report(main(parse_args()))
