"""A voxel pyramid's kernel maps in one compiled pass (`KernelMapCache.build_pyramid`) against the maps built one by
one (`build_kernel_map`, the pure-PyTorch path): coordinates, neighbour tables, pair counts, on batches with negative
coordinates, blobs and scattered voxels; the cases it declines; a MinkUNet's output with and without it."""

from __future__ import annotations

import pytest
import torch

from models.segmenter.minkunet import BASE_WIDTHS, MinkUNet
from models.sparse import SparseTensor, compiled
from models.sparse.kernel_map import pack_keys
from models.sparse.tensor import KernelMapCache

LEVELS = 5


@pytest.fixture(scope="module", autouse=True)
def built_engine():
    """These test the compiled pass itself: it runs even where RADARSEG_SPARSE_KERNELS forces the reference engine."""
    compiled.load()
    with compiled.using_kernels("compiled"):
        yield


def sorted_voxels(seed: int, per_sample: int, batch_size: int, spread: int, low: int) -> torch.Tensor:
    """Unique voxels (N, 4) sorted by key: `per_sample` draws per sample in [low, low + spread)^3."""
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for batch in range(batch_size):
        xyz = torch.randint(low, low + spread, (per_sample, 3), generator=generator)
        rows.append(torch.cat([torch.full((per_sample, 1), batch), xyz], dim=1))
    coords = torch.unique(torch.cat(rows), dim=0)
    return coords[torch.argsort(pack_keys(coords[:, 0], coords[:, 1:]))]


def one_by_one(coords: torch.Tensor) -> KernelMapCache:
    cache = KernelMapCache(coords, 1)
    with compiled.using_kernels("reference"):
        for level in range(LEVELS):
            cache.kernel_map(1 << level, 3, 1)
            if level + 1 < LEVELS:
                cache.kernel_map(1 << level, 2, 2)
    return cache


@pytest.mark.parametrize(
    ("per_sample", "batch_size", "spread", "low"),
    [(3000, 1, 12, 0), (400, 3, 40, -20), (1, 2, 5, 7), (2000, 2, 300, -150)],
    ids=["blob", "batch-negative", "one-voxel-each", "scattered"],
)
def test_the_pyramid_equals_the_maps_built_one_by_one(per_sample, batch_size, spread, low):
    coords = sorted_voxels(7, per_sample, batch_size, spread, low)
    expected = one_by_one(coords)
    cache = KernelMapCache(coords, 1)
    assert cache.build_pyramid(1, LEVELS)
    assert cache.num_maps == 2 * LEVELS - 1
    for level in range(LEVELS):
        assert torch.equal(cache.coords(1 << level), expected.coords(1 << level)), level
    for key, reference in expected._maps.items():
        built = cache._maps[key]
        assert torch.equal(built.neighbours, reference.neighbours), key
        assert built.pair_counts == reference.pair_counts, key
        assert (built.num_in, built.num_out, built.identity_offset, built.out_order) == (
            reference.num_in, reference.num_out, reference.identity_offset, reference.out_order), key


def test_unsorted_or_empty_voxels_and_the_reference_engine_are_left_to_the_one_by_one_path():
    coords = sorted_voxels(3, 500, 1, 10, 0)
    shuffled = coords[torch.randperm(len(coords), generator=torch.Generator().manual_seed(0))]
    assert not KernelMapCache(shuffled, 1).build_pyramid(1, LEVELS)
    assert not KernelMapCache(coords[:0], 1).build_pyramid(1, LEVELS)
    with compiled.using_kernels("reference"):
        assert not KernelMapCache(coords, 1).build_pyramid(1, LEVELS)
    cache = KernelMapCache(coords, 1)
    cache.kernel_map(1, 3, 1)
    first = cache._maps[(1, 3, 1)]
    assert cache.build_pyramid(1, LEVELS)
    assert cache._maps[(1, 3, 1)] is first  # a map built already is kept


def test_a_minkunet_gives_the_same_logits_with_and_without_the_pyramid(monkeypatch):
    torch.manual_seed(0)
    model = MinkUNet(in_channels=2, num_classes=4, widths=[max(4, w // 4) for w in BASE_WIDTHS]).eval()
    coords = sorted_voxels(11, 1500, 2, 16, 0)
    feats = torch.randn(len(coords), 2)
    built = []
    original = KernelMapCache.build_pyramid
    monkeypatch.setattr(KernelMapCache, "build_pyramid",
                        lambda self, stride, levels: built.append(original(self, stride, levels)) or built[-1])
    with torch.no_grad():
        with_pyramid = model(SparseTensor(coords, feats))
        assert built == [True]
        monkeypatch.setattr(KernelMapCache, "build_pyramid", lambda self, stride, levels: False)
        without = model(SparseTensor(coords, feats))
    torch.testing.assert_close(with_pyramid, without, rtol=1e-5, atol=1e-5)
