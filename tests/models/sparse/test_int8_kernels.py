"""The int8 sparse kernels against an integer reference in torch (int64 sums of the same products): the int32
accumulators equal exactly, on random maps, in the build this CPU runs and, on an AVX-512 machine, in the AVX2 build
too; the epilogue (scale, bias, residual, ReLU, requantisation) against the same formula in float32.

The kernels must build here (g++ and ninja are on every machine of ours): a failed build fails these tests."""

from __future__ import annotations

import pytest
import torch

from models.sparse import compiled, int8


def builds() -> list[str]:
    """The builds this CPU runs: its own, and the AVX2 one where it has AVX-512 (where it has not, native is it)."""
    flags = compiled.cpu_flags().split()
    return ["native", "avx2"] if "avx512f" in flags and "avx2" in flags else ["native"]


@pytest.fixture(scope="module", params=builds())
def kernels(request):
    return int8.load() if request.param == "native" else int8.build(request.param)


def random_table(generator: torch.Generator, rows: int, offsets: int, num_in: int, missing: float) -> torch.Tensor:
    table = torch.randint(0, max(num_in, 1), (rows, offsets), generator=generator)
    table[torch.rand(rows, offsets, generator=generator) < missing] = num_in
    return table if num_in else torch.full_like(table, num_in)


def reference(src: torch.Tensor, table: torch.Tensor, weight: torch.Tensor, zero_point: int) -> torch.Tensor:
    """sum_k (src[table[j, k]] - zero_point) . weight[k], missing neighbours skipped, in int64."""
    padded = torch.cat([src.long() - zero_point, torch.zeros(1, src.shape[1], dtype=torch.long)])
    gathered = padded[table.clamp(max=len(src))]  # (M, K, C); missing -> the zero row
    return torch.einsum("mkc,kcd->md", gathered, weight.long())


# Widths covering every column chunk (8, 16 + 8 on AVX-512, 3 and 2 + 2 wide vectors) and the extremes of both
# operands (activations 0..255, weights -128..127: int16 pair sums that `vpmaddubsw` would saturate).
CASES = [(4, 8), (8, 8), (24, 24), (32, 40), (12, 56), (64, 64), (96, 96)]


@pytest.mark.parametrize(("c_in", "c_out"), CASES)
@pytest.mark.parametrize("zero_point", [0, 128])
@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32])
def test_int32_accumulators_equal_the_integer_reference(kernels, c_in, c_out, zero_point, index_dtype):
    generator = torch.Generator().manual_seed(c_in * 100 + c_out + zero_point)
    n, k = 700, 27
    src = torch.randint(0, 256, (n, c_in), generator=generator, dtype=torch.uint8)
    src[:10] = 255  # the largest products
    weight = torch.randint(-128, 128, (k, c_in, c_out), generator=generator, dtype=torch.int8)
    weight[0, :, :3] = -128
    table = random_table(generator, n, k, n, missing=0.5)
    table[:10, 0] = torch.arange(10)
    sums = weight.sum(dim=1, dtype=torch.int32).contiguous()
    got = kernels.neighbour_conv_int8_raw(src, table.to(index_dtype), kernels.pack_weight(weight), c_out, zero_point,
                                          sums if zero_point else None)
    assert got.dtype == torch.int32
    assert torch.equal(got.long(), reference(src, table, weight, zero_point))


def test_empty_maps_and_missing_rows(kernels):
    weight = torch.ones(8, 4, 8, dtype=torch.int8)
    packed = kernels.pack_weight(weight)
    empty = kernels.neighbour_conv_int8_raw(torch.zeros(0, 4, dtype=torch.uint8), torch.zeros(0, 8, dtype=torch.long),
                                            packed, 8, 0, None)
    assert empty.shape == (0, 8)
    src = torch.full((3, 4), 7, dtype=torch.uint8)
    table = torch.full((5, 8), 3)  # nothing present
    got = kernels.neighbour_conv_int8_raw(src, table, packed, 8, 0, None)
    assert torch.equal(got, torch.zeros(5, 8, dtype=torch.int32))


def epilogue_reference(acc: torch.Tensor, scale, bias, residual, residual_scale, relu, out_scale):
    value = acc.float() * scale + bias
    if residual is not None:
        value = value + (residual.float() * residual_scale if residual.dtype == torch.uint8 else residual)
    if relu:
        value = value.clamp(min=0)
    if out_scale is None:
        return value
    return torch.round((value * (1.0 / out_scale)).clamp(0, 255))


@pytest.mark.parametrize("residual_kind", [None, "uint8", "float"])
@pytest.mark.parametrize("requantize", [False, True])
def test_the_fused_epilogue(kernels, residual_kind, requantize):
    generator = torch.Generator().manual_seed(3)
    n, k, c_in, c_out = 300, 27, 16, 24
    src = torch.randint(0, 256, (n, c_in), generator=generator, dtype=torch.uint8)
    weight = torch.randint(-127, 128, (k, c_in, c_out), generator=generator, dtype=torch.int8)
    table = random_table(generator, n, k, n, missing=0.5)
    scale = torch.rand(c_out, generator=generator) * 1e-4
    bias = torch.randn(c_out, generator=generator)
    residual = residual_scale = None
    if residual_kind == "uint8":
        residual = torch.randint(0, 256, (n, c_out), generator=generator, dtype=torch.uint8)
        residual_scale = torch.rand(c_out, generator=generator) * 0.01
    elif residual_kind == "float":
        residual = torch.randn(n, c_out, generator=generator)
    out_scale = (0.02 + 0.05 * torch.rand(c_out, generator=generator)) if requantize else None
    packed = kernels.pack_weight(weight)
    got = kernels.neighbour_conv_int8(src, table, packed, 0, None, scale, bias, residual, residual_scale, True,
                                      out_scale)
    acc = kernels.neighbour_conv_int8_raw(src, table, packed, c_out, 0, None)
    expected = epilogue_reference(acc, scale, bias, residual, residual_scale, True, out_scale)
    if requantize:
        assert got.dtype == torch.uint8
        assert (got.float() - expected).abs().max() <= 1  # one step where float rounding meets a tie
        assert (got.float() != expected).float().mean() < 0.01
    else:
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize(("rows", "c_in", "c_out"), [(700, 24, 24), (64, 8, 8), (1, 4, 40), (0, 8, 16)])
def test_compact_pairs_give_the_table_s_result(kernels, rows, c_in, c_out):
    """The gather kernel over compact pairs (each block's present pairs per offset) equals it over the table."""
    generator = torch.Generator().manual_seed(rows + c_in)
    src = torch.randint(0, 256, (max(rows, 1), c_in), generator=generator, dtype=torch.uint8)
    weight = torch.randint(-128, 128, (27, c_in, c_out), generator=generator, dtype=torch.int8)
    table = random_table(generator, rows, 27, len(src), missing=0.5)
    packed = kernels.pack_weight(weight)
    scale, bias = torch.rand(c_out, generator=generator) * 1e-3, torch.randn(c_out, generator=generator)
    out_scale = torch.full((c_out,), 0.05)
    residual = torch.randint(0, 256, (rows, c_out), generator=generator, dtype=torch.uint8)
    pairs = kernels.compact_pairs(table, len(src))
    assert len(pairs[2]) == int((table < len(src)).sum())
    for requantize in (None, out_scale):
        by_table = kernels.neighbour_conv_int8(src, table, packed, 0, None, scale, bias, residual, scale, True,
                                               requantize)
        by_pairs = kernels.neighbour_conv_int8_pairs(src, *pairs, rows, 27, packed, 0, None, scale, bias, residual,
                                                     scale, True, requantize)
        assert torch.equal(by_table, by_pairs)
    with pytest.raises(RuntimeError, match="compact_pairs' offsets"):
        kernels.neighbour_conv_int8_pairs(src, pairs[0][:-1], pairs[1], pairs[2], rows, 27, packed, 0, None, scale,
                                          None, None, None, False, None)


def test_scatter_reaches_each_output_once(kernels):
    generator = torch.Generator().manual_seed(4)
    n, c_in, c_out = 200, 24, 40
    num_out = n * 4
    slots = torch.randperm(n * 8, generator=generator).reshape(n, 8)
    table = torch.where(slots < num_out, slots, torch.full_like(slots, num_out))
    src = torch.randint(0, 256, (n, c_in), generator=generator, dtype=torch.uint8)
    weight = torch.randint(-128, 128, (8, c_in, c_out), generator=generator, dtype=torch.int8)
    scale = torch.full((c_out,), 1.0)
    got = kernels.scatter_conv_int8(src, table, kernels.pack_weight(weight), num_out, 0, None, scale, None, False,
                                    None)
    expected = torch.zeros(num_out + 1, c_out, dtype=torch.long)
    products = torch.einsum("mc,kcd->mkd", src.long(), weight.long())  # (M, 8, D)
    expected[table.reshape(-1)] = products.reshape(-1, c_out)
    assert torch.equal(got.long(), expected[:num_out])


def test_bad_inputs_are_refused_in_one_line(kernels):
    packed = kernels.pack_weight(torch.zeros(1, 4, 8, dtype=torch.int8))
    table = torch.zeros(2, 1, dtype=torch.long)
    with pytest.raises(RuntimeError, match="uint8 features"):
        kernels.neighbour_conv_int8_raw(torch.zeros(2, 4), table, packed, 8, 0, None)
    with pytest.raises(RuntimeError, match="multiple of 4"):
        kernels.pack_weight(torch.zeros(1, 6, 8, dtype=torch.int8))
    with pytest.raises(RuntimeError, match="packed by this build"):
        kernels.neighbour_conv_int8_raw(torch.zeros(2, 8, dtype=torch.uint8), table, packed, 8, 0, None)
    with pytest.raises(RuntimeError, match="weight_sums"):
        kernels.neighbour_conv_int8_raw(torch.zeros(2, 4, dtype=torch.uint8), table, packed, 8, 5, None)
    with pytest.raises(RuntimeError, match="out_scale must be finite and > 0"):
        kernels.neighbour_conv_int8(torch.zeros(2, 4, dtype=torch.uint8), table, packed, 0, None, torch.ones(8), None,
                                    None, None, True, torch.zeros(8))


def test_this_cpu_runs_vnni_where_it_has_it():
    flags = compiled.cpu_flags().split()
    expected = "avx512-vnni" if {"avx512f", "avx512_vnni", "avx512vl"} <= set(flags) else (
        "avx-vnni" if "avx_vnni" in flags else "avx2" if "avx2" in flags else "scalar")
    assert int8.path() == expected
