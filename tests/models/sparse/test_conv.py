"""The sparse convolutions against dense PyTorch convolutions on a densified grid, values and gradients.

These run the pure-PyTorch engine (its two paths, its MAC counts); tests/models/sparse/test_compiled.py
compares the compiled engine with it.
"""

from __future__ import annotations

import itertools

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

import models.sparse.tensor as sparse_tensor_module
from models.sparse import (
    PointwiseConv,
    SparseTensor,
    StridedConv3d,
    SubmanifoldConv3d,
    TransposedConv3d,
    compiled,
    last_forward_executed_macs,
    last_forward_macs,
)

DTYPE = torch.float64  # tight tolerances: the sparse and dense sums run in different orders


@pytest.fixture(autouse=True)
def torch_engine():
    with compiled.using_kernels("reference"):
        yield


def random_coords(
    generator: torch.Generator, *, num_per_sample: int, extent: int, batch_size: int, shared: int = 0
) -> Tensor:
    """Unique voxels (N, 4) in [0, extent)^3 per sample; the first `shared` voxels of sample 0 are
    repeated in every other sample, so samples overlap and only the batch index separates them."""
    rows = []
    first = None
    for batch in range(batch_size):
        flat = torch.randperm(extent**3, generator=generator)[:num_per_sample]
        if first is not None and shared:
            flat = torch.cat([first[:shared], flat[~torch.isin(flat, first[:shared])]])[:num_per_sample]
        first = flat if first is None else first
        xyz = torch.stack([flat // extent**2, (flat // extent) % extent, flat % extent], dim=1)
        rows.append(torch.cat([torch.full((len(flat), 1), batch), xyz], dim=1))
    return torch.cat(rows)


def densify(coords: Tensor, feats: Tensor, batch_size: int, extent: int) -> Tensor:
    """(N, C) features -> dense (B, C, X, Y, Z) grid, differentiable in `feats`."""
    grid = feats.new_zeros(batch_size, extent, extent, extent, feats.shape[1])
    grid = grid.index_put(tuple(coords.T), feats)
    return grid.permute(0, 4, 1, 2, 3)


def read_dense(dense: Tensor, coords: Tensor) -> Tensor:
    """Dense (B, C, X, Y, Z) read at voxels (N, 4) -> (N, C)."""
    return dense.permute(0, 2, 3, 4, 1)[tuple(coords.T)]


def dense_weight(weight: Tensor, kernel_size: int, *, transposed: bool) -> Tensor:
    """Our [K, C_in, C_out] weight as conv3d's [C_out, C_in, k, k, k] (transposed: [C_in, C_out, k, k, k])."""
    k = kernel_size
    grid = weight.reshape(k, k, k, weight.shape[1], weight.shape[2])
    return grid.permute(3, 4, 0, 1, 2) if transposed else grid.permute(4, 3, 0, 1, 2)


def check_against_dense(sparse_fn, dense_fn, coords: Tensor, feats: Tensor, weight: Tensor, generator):
    """Run both paths with the same loss sum(out * probe) and assert equal outputs and gradients."""
    feats_sparse = feats.clone().requires_grad_(True)
    out_sparse, out_coords = sparse_fn(feats_sparse)
    probe = torch.randn(out_sparse.shape, generator=generator, dtype=DTYPE)
    (out_sparse * probe).sum().backward()
    grad_weight_sparse = weight.grad.clone()
    weight.grad = None

    feats_dense = feats.clone().requires_grad_(True)
    out_dense = dense_fn(feats_dense, out_coords)
    (out_dense * probe).sum().backward()

    torch.testing.assert_close(out_sparse, out_dense)
    torch.testing.assert_close(feats_sparse.grad, feats_dense.grad)
    torch.testing.assert_close(grad_weight_sparse, weight.grad)


PATHS = ["per_offset", "gemm"]


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("kernel_size", [3, 5])
def test_submanifold_conv_matches_dense_conv3d(kernel_size, path):
    generator = torch.Generator().manual_seed(kernel_size)
    extent, batch_size = 9, 2
    coords = random_coords(generator, num_per_sample=150, extent=extent, batch_size=batch_size, shared=100)
    feats = torch.randn(len(coords), 5, generator=generator, dtype=DTYPE)
    conv = SubmanifoldConv3d(5, 7, kernel_size).to(DTYPE)
    conv.path = path

    def sparse_fn(f):
        out = conv(SparseTensor(coords, f))
        return out.feats, out.coords

    def dense_fn(f, out_coords):
        weight = dense_weight(conv.weight, kernel_size, transposed=False)
        dense = F.conv3d(densify(coords, f, batch_size, extent), weight, padding=kernel_size // 2)
        return read_dense(dense, out_coords)

    check_against_dense(sparse_fn, dense_fn, coords, feats, conv.weight, generator)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("tensor_stride", [1, 2])
def test_strided_conv_matches_dense_conv3d(tensor_stride, path):
    generator = torch.Generator().manual_seed(10 + tensor_stride)
    extent, batch_size = 10, 2
    coords = random_coords(generator, num_per_sample=200, extent=extent, batch_size=batch_size, shared=150)
    feats = torch.randn(len(coords), 4, generator=generator, dtype=DTYPE)
    conv = StridedConv3d(4, 6).to(DTYPE)
    conv.path = path
    # A tensor already at tensor stride 2 (its coordinates are in units of 2 finest voxels) behaves the
    # same on its own grid: the strided conv takes it to stride 4.
    cache_stride = tensor_stride

    def sparse_fn(f):
        out = conv(SparseTensor(coords, f, cache_stride))
        assert out.stride == 2 * cache_stride
        return out.feats, out.coords

    def dense_fn(f, out_coords):
        weight = dense_weight(conv.weight, 2, transposed=False)
        dense = F.conv3d(densify(coords, f, batch_size, extent), weight, stride=2)
        return read_dense(dense, out_coords)

    check_against_dense(sparse_fn, dense_fn, coords, feats, conv.weight, generator)


def test_strided_conv_output_voxels_are_unique_halved_coordinates():
    generator = torch.Generator().manual_seed(3)
    coords = random_coords(generator, num_per_sample=80, extent=8, batch_size=2, shared=40)
    out = StridedConv3d(1, 1)(SparseTensor(coords, torch.ones(len(coords), 1)))
    expected = {(int(b), int(x) // 2, int(y) // 2, int(z) // 2) for b, x, y, z in coords}
    assert {tuple(row) for row in out.coords.tolist()} == expected
    assert len(out) == len(expected)


@pytest.mark.parametrize("path", PATHS)
def test_transposed_conv_matches_dense_conv_transpose3d_and_reuses_the_strided_map(monkeypatch, path):
    generator = torch.Generator().manual_seed(4)
    extent, batch_size = 10, 2
    fine_coords = random_coords(generator, num_per_sample=200, extent=extent, batch_size=batch_size, shared=150)
    builds = []
    real_build = sparse_tensor_module.build_kernel_map

    def counting_build(*args, **kwargs):
        builds.append((args[2], args[3]))  # (kernel_size, stride)
        return real_build(*args, **kwargs)

    monkeypatch.setattr(sparse_tensor_module, "build_kernel_map", counting_build)
    fine = SparseTensor(fine_coords, torch.zeros(len(fine_coords), 3, dtype=DTYPE))
    coarse = StridedConv3d(3, 3).to(DTYPE)(fine)
    assert builds == [(2, 2)]
    feats = torch.randn(len(coarse), 3, generator=generator, dtype=DTYPE)
    conv = TransposedConv3d(3, 5).to(DTYPE)
    conv.path = path

    def sparse_fn(f):
        out = conv(coarse.replace_feats(f))
        assert out.stride == 1 and out.coords is fine_coords
        return out.feats, out.coords

    def dense_fn(f, out_coords):
        coarse_extent = extent // 2
        weight = dense_weight(conv.weight, 2, transposed=True)
        dense = F.conv_transpose3d(densify(coarse.coords, f, batch_size, coarse_extent), weight, stride=2)
        return read_dense(dense, out_coords)

    check_against_dense(sparse_fn, dense_fn, coarse.coords, feats, conv.weight, generator)
    assert builds == [(2, 2)], "the transposed conv must reuse the strided conv's kernel map"


def test_submanifold_map_is_built_once_and_identity_offset_skips_the_search(monkeypatch):
    generator = torch.Generator().manual_seed(5)
    coords = random_coords(generator, num_per_sample=60, extent=6, batch_size=1)
    x = SparseTensor(coords, torch.randn(len(coords), 2, generator=generator))
    first, second = SubmanifoldConv3d(2, 2), SubmanifoldConv3d(2, 2)
    first.path = "per_offset"
    second(first(x))
    assert x.cache.num_maps == 1
    kernel_map = x.cache.kernel_map(1, 3, 1)
    assert kernel_map.identity_offset == 13  # (0, 0, 0) is the centre of itertools.product order
    assert torch.equal(kernel_map.in_indices[13], torch.arange(len(coords)))

    # The identity offset must not go through index_select: count calls while running the conv.
    calls = []
    real_index_select = torch.Tensor.index_select

    def counting_index_select(self, dim, index):
        calls.append(len(index))
        return real_index_select(self, dim, index)

    monkeypatch.setattr(torch.Tensor, "index_select", counting_index_select)
    first(x)
    non_empty = sum(1 for k, count in enumerate(kernel_map.pair_counts) if count and k != 13)
    assert len(calls) == non_empty


def brute_force_pairs(in_coords: Tensor, out_coords: Tensor, offsets, stride: int) -> int:
    """Pairs (output q, offset d) whose input voxel stride*q + d exists, by Python set lookups."""
    present = {tuple(row) for row in in_coords.tolist()}
    pairs = 0
    for b, x, y, z in out_coords.tolist():
        for dx, dy, dz in offsets:
            pairs += (b, stride * x + dx, stride * y + dy, stride * z + dz) in present
    return pairs


@pytest.mark.parametrize("path", PATHS)
def test_mac_counts_equal_brute_force_pair_counts(path):
    generator = torch.Generator().manual_seed(6)
    coords = random_coords(generator, num_per_sample=120, extent=7, batch_size=2, shared=60)
    x = SparseTensor(coords, torch.randn(len(coords), 3, generator=generator))
    sub, down, up, pointwise = (
        SubmanifoldConv3d(3, 4),
        StridedConv3d(4, 5),
        TransposedConv3d(5, 2),
        PointwiseConv(2, 6),
    )
    model = torch.nn.ModuleList([sub, down, up, pointwise])
    for conv in (sub, down, up):
        conv.path = path
    coarse = down(sub(x))
    pointwise(up(coarse))

    centred = list(itertools.product(range(-1, 2), repeat=3))
    corner = list(itertools.product(range(2), repeat=3))
    sub_pairs = brute_force_pairs(coords, coords, centred, 1)
    down_pairs = brute_force_pairs(coords, coarse.coords, corner, 2)
    assert sub.last_macs == sub_pairs * 3 * 4
    assert down_pairs == len(coords)  # every fine voxel has exactly one coarse parent
    assert down.last_macs == down_pairs * 4 * 5
    assert up.last_macs == down_pairs * 5 * 2
    assert pointwise.last_macs == len(coords) * 2 * 6
    assert last_forward_macs(model) == sub.last_macs + down.last_macs + up.last_macs + pointwise.last_macs
    executed = {"per_offset": (sub_pairs, down_pairs, down_pairs),  # pairs; the GEMM path: every slot
                "gemm": (len(coords) * 27, len(coarse) * 8, len(coarse) * 8)}[path]
    assert (sub.last_executed_macs, down.last_executed_macs, up.last_executed_macs) == (
        executed[0] * 3 * 4, executed[1] * 4 * 5, executed[2] * 5 * 2)
    assert last_forward_executed_macs(model) == sum(m.last_executed_macs for m in model)


def test_negative_coordinates_behave_like_shifted_positive_ones():
    generator = torch.Generator().manual_seed(7)
    coords = random_coords(generator, num_per_sample=100, extent=8, batch_size=2, shared=50)
    feats = torch.randn(len(coords), 3, generator=generator)
    layers = torch.nn.Sequential(SubmanifoldConv3d(3, 3), StridedConv3d(3, 3), TransposedConv3d(3, 3))
    shift = torch.tensor([0, -20, 6, -4])  # even, so the stride-2 grid aligns the same way
    reference = layers(SparseTensor(coords, feats)).feats
    shifted = layers(SparseTensor(coords + shift, feats)).feats
    torch.testing.assert_close(shifted, reference)


def test_bad_coordinates_are_rejected():
    feats = torch.zeros(2, 1)
    with pytest.raises(ValueError, match="duplicate"):
        SubmanifoldConv3d(1, 1)(SparseTensor(torch.tensor([[0, 1, 2, 3], [0, 1, 2, 3]]), feats))
    with pytest.raises(ValueError, match="int64"):
        SparseTensor(torch.zeros(2, 4, dtype=torch.int32), feats)
    with pytest.raises(ValueError, match=r"\|c\|"):
        SparseTensor(torch.tensor([[0, 0, 0, 0], [0, 40000, 0, 0]]), feats)
    with pytest.raises(ValueError, match="input channels"):
        SubmanifoldConv3d(2, 1)(SparseTensor(torch.tensor([[0, 0, 0, 0], [1, 0, 0, 0]]), feats))


@pytest.mark.parametrize(("kernel_size", "stride"), [(3, 1), (5, 1), (2, 2)])
def test_grid_index_and_hashing_build_the_same_maps(kernel_size, stride):
    from models.sparse.kernel_map import VoxelIndex, build_kernel_map, downsample_coords

    generator = torch.Generator().manual_seed(8)
    coords = random_coords(generator, num_per_sample=150, extent=9, batch_size=3, shared=80)
    coords = coords + torch.tensor([1, -7, 3, -2])  # batch indices need not start at 0
    out_coords = coords if stride == 1 else downsample_coords(coords, stride)
    grid, hashed = VoxelIndex(coords), VoxelIndex(coords, max_cells=0)
    assert grid.uses_grid and not hashed.uses_grid
    maps = [build_kernel_map(index, out_coords, kernel_size, stride, same_coords=stride == 1)
            for index in (grid, hashed)]
    assert torch.equal(maps[0].neighbours, maps[1].neighbours)
    assert maps[0].pair_counts == maps[1].pair_counts
    centred = list(itertools.product(range(-(kernel_size // 2), kernel_size // 2 + 1), repeat=3))
    offsets = centred if stride == 1 else list(itertools.product(range(stride), repeat=3))
    assert maps[0].num_pairs == brute_force_pairs(coords, out_coords, offsets, stride)


def test_choose_path_follows_the_measured_rule():
    from models.sparse import choose_path
    from models.sparse.kernel_map import VoxelIndex, build_kernel_map, downsample_coords
    from models.sparse.paths import GEMM_MAX_IN_CHANNELS

    generator = torch.Generator().manual_seed(3)
    coords = random_coords(generator, num_per_sample=500, extent=9, batch_size=1)  # dense blob: fill >= 0.25
    index = VoxelIndex(coords)
    sub = build_kernel_map(index, coords, 3, 1, same_coords=True)
    down = build_kernel_map(index, downsample_coords(coords, 2), 2, 2, same_coords=False)
    narrow, wide = GEMM_MAX_IN_CHANNELS, GEMM_MAX_IN_CHANNELS + 8
    assert choose_path(sub, narrow, narrow, transposed=False) == "gemm"
    assert choose_path(sub, wide, wide, transposed=False) == "per_offset"
    assert choose_path(down, wide, wide, transposed=False) == "gemm"  # down-sampling: GEMM at every width
    assert choose_path(down, narrow, narrow, transposed=True) == "gemm"
    assert choose_path(down, wide, wide, transposed=True) == "per_offset"  # up-sampling wide: per offset
    sparse = build_kernel_map(VoxelIndex(coords[::9] * 3), coords[::9] * 3, 3, 1, same_coords=True)
    assert choose_path(sparse, narrow, narrow, transposed=False) == "per_offset"  # fill < GEMM_MIN_FILL


def test_choose_path_takes_the_gemm_on_large_well_filled_maps_at_any_width():
    from models.sparse import choose_path
    from models.sparse.kernel_map import VoxelIndex, build_kernel_map
    from models.sparse.paths import GEMM_WIDE_MIN_VOXELS

    side = 27  # a solid cube of 27^3 voxels: fill about 0.9
    xyz = torch.stack(torch.meshgrid(*[torch.arange(side)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    coords = torch.cat([torch.zeros(len(xyz), 1, dtype=torch.int64), xyz], dim=1)
    assert len(coords) >= GEMM_WIDE_MIN_VOXELS
    solid = build_kernel_map(VoxelIndex(coords), coords, 3, 1, same_coords=True)
    assert choose_path(solid, 64, 64, transposed=False) == "gemm"
    half = coords[: GEMM_WIDE_MIN_VOXELS // 2]  # as well filled, too few voxels: per offset above 16 channels
    small = build_kernel_map(VoxelIndex(half), half, 3, 1, same_coords=True)
    assert choose_path(small, 64, 64, transposed=False) == "per_offset"
