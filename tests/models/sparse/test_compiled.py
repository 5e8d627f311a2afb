"""The compiled sparse engine against the pure-PyTorch one: outputs and gradients (features and weight) of
every convolution kind, on random maps including empty inputs and single voxels; the engine setting.

The compiled engine must build here (g++ and ninja are on every machine of ours): a failed build fails
these tests instead of skipping them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from models.sparse import SparseTensor, StridedConv3d, SubmanifoldConv3d, TransposedConv3d, compiled

RELATIVE = 1e-5


@pytest.fixture(scope="module", autouse=True)
def built_engine():
    compiled.load()  # raises with the compiler's first line when the build fails


def random_coords(generator: torch.Generator, num_voxels: int, extent: int, batch_size: int) -> torch.Tensor:
    """Unique voxels (N, 4): `num_voxels` per sample in [0, extent)^3, in random order."""
    rows = []
    for batch in range(batch_size):
        flat = torch.randperm(extent**3, generator=generator)[:num_voxels]
        xyz = torch.stack([flat // extent**2, (flat // extent) % extent, flat % extent], dim=1)
        rows.append(torch.cat([torch.full((len(flat), 1), batch), xyz], dim=1))
    return torch.cat(rows)[torch.randperm(num_voxels * batch_size, generator=generator)]


def run(engine: str, conv: torch.nn.Module, x: SparseTensor, probe_seed: int):
    """Output features, input gradient and weight gradient of `sum(conv(x) * probe)` on one engine."""
    feats = x.feats.detach().clone().requires_grad_(True)
    conv.weight.grad = None
    with compiled.using_kernels(engine):
        out = conv(x.replace_feats(feats)).feats
    probe = torch.randn(out.shape, generator=torch.Generator().manual_seed(probe_seed))
    (out * probe).sum().backward()
    grad_weight = conv.weight.grad.clone() if conv.weight.grad is not None else torch.zeros_like(conv.weight)
    grad_feats = feats.grad if feats.grad is not None else torch.zeros_like(feats)
    return out.detach(), grad_feats, grad_weight, conv.last_macs, conv.last_executed_macs


def assert_close_relative(native_value: torch.Tensor, reference: torch.Tensor, what: str) -> None:
    assert native_value.shape == reference.shape, what
    scale = float(reference.abs().max()) if reference.numel() else 0.0
    error = float((native_value - reference).abs().max()) if reference.numel() else 0.0
    assert error <= RELATIVE * max(scale, 1e-12), f"{what}: max error {error:.3g} against max |value| {scale:.3g}"


def check_engines_agree(conv: torch.nn.Module, x: SparseTensor, seed: int) -> None:
    fast, reference = run("compiled", conv, x, seed), run("reference", conv, x, seed)
    for name, a, b in zip(("output", "feature gradient", "weight gradient"), fast[:3], reference[:3],
                          strict=True):
        assert_close_relative(a, b, f"{type(conv).__name__} {name}")
    assert fast[3] == reference[3], "useful MACs"
    assert fast[4] == fast[3], "the compiled engine executes exactly the useful MACs"


CASES = [  # (voxels per sample, extent, batch size): sparse, dense, single voxel, empty
    (300, 12, 2),
    (400, 8, 1),
    (1, 4, 1),
    (0, 4, 1),
]
# Output widths that reach every column chunk of the micro-kernels on AVX2 (8 lanes) and AVX-512 (16 lanes):
# 8 (a half vector), 24 (16 + 8 on AVX-512), 40, 56 (three wide vectors and a half), 64 (two + two).
CHANNELS = [(1, 3), (8, 8), (13, 35), (32, 24), (20, 56), (48, 64)]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize(("c_in", "c_out"), CHANNELS)
@pytest.mark.parametrize("kernel_size", [3, 5])
def test_submanifold_engines_agree(case, c_in, c_out, kernel_size):
    generator = torch.Generator().manual_seed(c_in * 31 + kernel_size)
    coords = random_coords(generator, *case)
    x = SparseTensor(coords, torch.randn(len(coords), c_in, generator=generator))
    check_engines_agree(SubmanifoldConv3d(c_in, c_out, kernel_size), x, seed=c_out)


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize(("c_in", "c_out"), CHANNELS)
@pytest.mark.parametrize("tensor_stride", [1, 2, 4])
def test_strided_and_transposed_engines_agree(case, c_in, c_out, tensor_stride):
    generator = torch.Generator().manual_seed(c_in * 7 + tensor_stride)
    coords = random_coords(generator, *case)
    x = SparseTensor(coords * tensor_stride * torch.tensor([0, 1, 1, 1]) + coords * torch.tensor([1, 0, 0, 0]),
                     torch.randn(len(coords), c_in, generator=generator), tensor_stride)
    down = StridedConv3d(c_in, c_out)
    check_engines_agree(down, x, seed=1)
    with compiled.using_kernels("reference"):
        coarse = down(x)
    coarse = coarse.replace_feats(torch.randn(len(coarse), c_out, generator=generator))
    check_engines_agree(TransposedConv3d(c_out, c_in), coarse, seed=2)


def test_a_small_network_trains_the_same_on_both_engines():
    """Gradients through a chain (sub, down, sub, up) reach every weight alike on both engines."""
    generator = torch.Generator().manual_seed(11)
    coords = random_coords(generator, 250, 10, 2)
    feats = torch.randn(len(coords), 4, generator=generator)
    layers = torch.nn.Sequential(SubmanifoldConv3d(4, 8), StridedConv3d(8, 16), SubmanifoldConv3d(16, 16),
                                 TransposedConv3d(16, 8))
    grads = {}
    for engine in ("compiled", "reference"):
        layers.zero_grad(set_to_none=True)
        with compiled.using_kernels(engine):
            out = layers(SparseTensor(coords, feats)).feats
        out.square().sum().backward()
        grads[engine] = [p.grad.clone() for p in layers.parameters()]
    for fast, reference in zip(grads["compiled"], grads["reference"], strict=True):
        assert_close_relative(fast, reference, "chained weight gradient")


def test_float64_and_the_torch_setting_use_the_torch_engine(monkeypatch):
    calls = []
    monkeypatch.setattr(compiled, "neighbour_conv", lambda *args: calls.append(args) or torch.zeros(0))
    coords = random_coords(torch.Generator().manual_seed(1), 20, 5, 1)
    conv = SubmanifoldConv3d(2, 2)
    with compiled.using_kernels("auto"):
        conv.double()(SparseTensor(coords, torch.randn(20, 2, dtype=torch.float64)))
    with compiled.using_kernels("reference"):
        conv.float()(SparseTensor(coords, torch.randn(20, 2)))
    assert calls == []


def test_engine_setting_is_validated_and_read_from_the_environment(monkeypatch):
    with pytest.raises(ValueError, match="sparse kernels must be one of"):
        compiled.set_kernels("fast")
    previous = compiled.get_kernels()
    try:
        monkeypatch.setattr(compiled, "_kernels", None)
        monkeypatch.setenv(compiled.KERNELS_ENV, "Reference")
        assert compiled.get_kernels() == "reference"
        for old, new in (("native", "compiled"), ("torch", "reference")):  # an earlier name: the new one named
            monkeypatch.setattr(compiled, "_kernels", None)
            monkeypatch.setenv(compiled.KERNELS_ENV, old)
            expected = f"RADARSEG_SPARSE_KERNELS: sparse kernels '{old}' are now called '{new}'"
            with pytest.raises(ValueError, match=expected):
                compiled.get_kernels()
        monkeypatch.setattr(compiled, "_kernels", None)
        monkeypatch.setenv(compiled.KERNELS_ENV, "gpu")
        with pytest.raises(ValueError, match="RADARSEG_SPARSE_KERNELS"):
            compiled.get_kernels()
        monkeypatch.setattr(compiled, "_kernels", None)  # the variable's earlier name: refused naming the new one
        monkeypatch.setenv(compiled.OLD_KERNELS_ENV, "reference")
        with pytest.raises(ValueError, match="RADARSEG_SPARSE_ENGINE is now RADARSEG_SPARSE_KERNELS"):
            compiled.get_kernels()
    finally:
        compiled.set_kernels(previous)


def test_a_failed_build_falls_back_with_one_warning_under_auto_and_raises_under_compiled(monkeypatch):
    monkeypatch.setattr(compiled, "_module", None)
    monkeypatch.setattr(compiled, "_build_error", "the compiled sparse kernels did not build (no compiler)")
    monkeypatch.setattr(compiled, "_warned", False)
    coords = random_coords(torch.Generator().manual_seed(2), 30, 5, 1)
    x = SparseTensor(coords, torch.randn(30, 3))
    conv = SubmanifoldConv3d(3, 2)
    with compiled.using_kernels("auto"), pytest.warns(RuntimeWarning, match="pure-PyTorch") as record:
        conv(x)
        conv(x)
    assert len([w for w in record if issubclass(w.category, RuntimeWarning)]) == 1
    with compiled.using_kernels("compiled"), pytest.raises(RuntimeError, match="did not build"):
        conv(x)


def test_the_avx2_kernels_agree_with_the_avx512_ones_where_the_cpu_has_both():
    """On an AVX-512 machine the engine runs 16-lane micro-kernels; the 8-lane AVX2 ones that other machines
    run are built here too and must give the same sums (every kernel, every column chunk, ragged row groups)."""
    if "avx512f" not in compiled.cpu_flags().split():
        pytest.skip("this CPU has no AVX-512: the engine under test above is the AVX2 build")
    wide, narrow = compiled.load(), compiled.build("avx2")
    generator = torch.Generator().manual_seed(5)
    n, k = 300, 27
    neighbours = torch.randint(0, n, (n, k), generator=generator)
    neighbours[torch.rand(n, k, generator=generator) < 0.5] = n
    for c_in, c_out in [(8, 8), (24, 24), (13, 40), (20, 56), (48, 64)]:
        src = torch.randn(n, c_in, generator=generator)
        weight = torch.randn(k, c_in, c_out, generator=generator)
        dense = torch.randn(n, c_out, generator=generator)
        for kernel, args in (("neighbour_conv", (src, neighbours, weight)),
                             ("neighbour_weight_grad", (src, neighbours, dense))):
            assert_close_relative(getattr(wide, kernel)(*args), getattr(narrow, kernel)(*args),
                                  f"{kernel} {c_in}x{c_out}")
        # A down-sampling map read backwards reaches each output row once: half of a permutation's slots
        # name an output row, the other half are missing (= num_out).
        num_out = n * 4
        slots = torch.randperm(n * 8, generator=generator).reshape(n, 8)
        targets = torch.where(slots < num_out, slots, torch.full_like(slots, num_out))
        weight8 = torch.randn(8, c_in, c_out, generator=generator)
        assert_close_relative(wide.scatter_conv(src, targets, weight8, num_out),
                              narrow.scatter_conv(src, targets, weight8, num_out), f"scatter_conv {c_in}x{c_out}")


@pytest.mark.parametrize(("kernel_size", "stride"), [(3, 1), (5, 1), (2, 2)])
def test_kernel_maps_read_from_the_grid_agree_on_both_engines(kernel_size, stride):
    """The compiled engine reads a map's neighbour table from the index grid in one pass (`grid_neighbours`)."""
    coords = random_coords(torch.Generator().manual_seed(kernel_size), 400, 12, 2)
    tables = {}
    for engine in ("compiled", "reference"):
        with compiled.using_kernels(engine):
            cache = SparseTensor(coords, torch.zeros(len(coords), 1)).cache
            tables[engine] = cache.kernel_map(1, kernel_size, stride)
        assert cache.index(1).uses_grid
    assert tables["compiled"].neighbours.dtype == torch.int64
    assert torch.equal(tables["compiled"].neighbours, tables["reference"].neighbours)
    assert tables["compiled"].pair_counts == tables["reference"].pair_counts
    with pytest.raises(RuntimeError, match="outside the grid"):
        compiled.grid_neighbours(torch.zeros(10, dtype=torch.int32), torch.tensor([9]), torch.tensor([0, 1]))


def test_a_lock_left_by_a_killed_build_does_not_block_the_next_process():
    """torch's build lock is a plain file: a build killed halfway leaves it and the next load would wait forever.
    Under our OS lock the left-over file is removed (in a child process, so that a hang fails by its timeout)."""
    script = ("from models.sparse import compiled\n"
              "d = compiled.build_directory('radarseg_sparse', 'native')\n"
              "d.mkdir(parents=True, exist_ok=True)\n"
              "(d / 'lock').write_text('left by a killed build')\n"
              "compiled.build('native')\n"
              "lock = d / 'lock'\n"  # another worker's own load may hold a fresh (empty) lock by now
              "print('loaded', lock.exists() and lock.read_text() == 'left by a killed build')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600,
                          cwd=Path(__file__).resolve().parents[3])
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "loaded False"
