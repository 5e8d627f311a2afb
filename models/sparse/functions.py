"""The autograd Functions behind a sparse convolution over a kernel map, one per way of running it:

- `_CompiledConv`: the compiled engine's kernels (`models.sparse.compiled`; CPU, float32), forward and backward;
- `_GatherMatmulScatter`: per kernel offset, gather the input rows, multiply by that offset's weight and
  scatter-add into the outputs (executes exactly the useful MACs);
- `_NeighbourGemm`: all offsets in one matrix product over the neighbour table, in cache-sized row chunks
  (executes `N_out x K x C_in x C_out`, missing neighbours as zero rows);
- `_PickProducts`: the transposed (up-sampling) conv as every child's product, each output picking its own.

Each saves what its backward needs and returns gradients for the features and the weight `[K, C_in, C_out]`.
Which one runs is `models.sparse.paths.apply_kernel_map`'s choice.
"""

from __future__ import annotations

import torch
from torch import Tensor

from models.sparse import compiled
from models.sparse.kernel_map import KernelMap


class _GatherMatmulScatter(torch.autograd.Function):
    """out[targets_k] += feats[sources_k] @ weight[k] over offsets k, with a hand-written backward.

    Autograd's own backward of `index_select` allocates a zero (N_in, C_in) gradient per offset and then
    sums them; here all offsets scatter into one gradient buffer, and the gathered inputs are gathered
    again in the backward instead of being kept alive between the passes.
    """

    @staticmethod
    def forward(ctx, feats, weight, sources, targets, pair_counts, identity, num_out):  # noqa: D102
        ctx.save_for_backward(feats, weight)
        ctx.plan = (sources, targets, pair_counts, identity)
        if identity is not None:
            # Centre offset of a submanifold conv: every voxel pairs with itself, no gather or scatter.
            out = feats @ weight[identity]
        else:
            out = feats.new_zeros(num_out, weight.shape[2])
        for offset, count in enumerate(pair_counts):
            if offset == identity or count == 0:
                continue
            gathered = feats.index_select(0, sources[offset])  # (P_k, C_in)
            out.index_add_(0, targets[offset], gathered @ weight[offset])
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        feats, weight = ctx.saved_tensors
        sources, targets, pair_counts, identity = ctx.plan
        need_feats, need_weight = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_feats = grad_weight = None
        if need_weight:
            grad_weight = torch.zeros_like(weight)
        if need_feats:
            if identity is not None:
                grad_feats = grad_out @ weight[identity].T
            else:
                grad_feats = torch.zeros_like(feats)
        if identity is not None and need_weight:
            grad_weight[identity] = feats.T @ grad_out
        for offset, count in enumerate(pair_counts):
            if offset == identity or count == 0:
                continue
            grad_rows = grad_out.index_select(0, targets[offset])  # (P_k, C_out)
            if need_feats:
                grad_feats.index_add_(0, sources[offset], grad_rows @ weight[offset].T)
            if need_weight:
                grad_weight[offset] = feats.index_select(0, sources[offset]).T @ grad_rows
        return grad_feats, grad_weight, None, None, None, None, None


def gather_neighbours(feats: Tensor, neighbours: Tensor) -> Tensor:
    """Features of every (row, offset) neighbour side by side, zeros where there is none.

    Args:
        feats: (N, C).
        neighbours: (M, K) int64 rows of `feats`, N for a missing neighbour.

    Returns:
        (M, K * C), block `k` of row `j` = `feats[neighbours[j, k]]`.
    """
    padded = torch.cat([feats, feats.new_zeros(1, feats.shape[1])])
    return padded.index_select(0, neighbours.reshape(-1)).view(neighbours.shape[0], -1)


def pick_products(feats: Tensor, weight: Tensor, slots: Tensor) -> Tensor:
    """`out[i] = feats[slots[i] // K] @ weight[slots[i] % K]`: one GEMM over all offsets, then a gather.

    Args:
        feats: (M, C_in).
        weight: (K, C_in, C_out).
        slots: (N,) int64 `row * K + k`.

    Returns:
        (N, C_out).
    """
    num_offsets, c_in, c_out = weight.shape
    products = feats @ weight.permute(1, 0, 2).reshape(c_in, num_offsets * c_out)  # (M, K * C_out)
    return products.view(-1, c_out).index_select(0, slots)


GEMM_CHUNK_BYTES = 4 << 20
"""Gathered rows per GEMM chunk are sized to about this many bytes, so they stay in cache between the
gather and the matrix product (unchunked, the (N, K x C) matrix is memory-bound: 2-3x slower)."""


def chunk_rows(row_bytes: int) -> int:
    """Rows per chunk of a gathered matrix whose rows take `row_bytes`."""
    return max(256, min(8192, GEMM_CHUNK_BYTES // max(1, row_bytes)))


def neighbour_gemm(feats: Tensor, neighbours: Tensor, weight_stacked: Tensor) -> Tensor:
    """`gather_neighbours(feats, neighbours) @ weight_stacked` in cache-sized chunks of rows.

    Args:
        feats: (N, C_in).
        neighbours: (M, K) int64 rows of `feats`, N where missing.
        weight_stacked: (K * C_in, C_out).

    Returns:
        (M, C_out).
    """
    padded = torch.cat([feats, feats.new_zeros(1, feats.shape[1])])
    num_rows, width = neighbours.shape[0], weight_stacked.shape[0]
    out = feats.new_empty(num_rows, weight_stacked.shape[1])
    step = chunk_rows(width * feats.element_size())
    for start in range(0, num_rows, step):
        rows = neighbours[start:start + step].reshape(-1)
        torch.mm(padded.index_select(0, rows).view(-1, width), weight_stacked, out=out[start:start + step])
    return out


def neighbour_weight_grad(feats: Tensor, neighbours: Tensor, grad_out: Tensor) -> Tensor:
    """`gather_neighbours(feats, neighbours).T @ grad_out` (K * C_in, C_out), chunked like `neighbour_gemm`."""
    padded = torch.cat([feats, feats.new_zeros(1, feats.shape[1])])
    width = neighbours.shape[1] * feats.shape[1]
    grad = feats.new_zeros(width, grad_out.shape[1])
    step = chunk_rows(width * feats.element_size())
    for start in range(0, neighbours.shape[0], step):
        gathered = padded.index_select(0, neighbours[start:start + step].reshape(-1)).view(-1, width)
        grad.addmm_(gathered.T, grad_out[start:start + step])
    return grad


class _NeighbourGemm(torch.autograd.Function):
    """Implicit GEMM: `out = gather_neighbours(feats) @ weight.view(K * C_in, C_out)`, in cache-sized chunks.

    Executes N_out x K x C_in x C_out MACs (missing neighbours multiply zeros) in 2 operations per chunk
    of rows instead of 3 per offset. The backward needs no scatter either: a submanifold map is its own
    transpose with offsets mirrored (`k <-> K-1-k`), and a down-sampling map gives each input exactly
    one (output, offset) slot.
    """

    @staticmethod
    def forward(ctx, feats, weight, kernel_map):  # noqa: D102
        ctx.save_for_backward(feats, weight)
        ctx.kernel_map = kernel_map
        num_offsets, c_in, c_out = weight.shape
        return neighbour_gemm(feats, kernel_map.neighbours, weight.reshape(num_offsets * c_in, c_out))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        feats, weight = ctx.saved_tensors
        kernel_map = ctx.kernel_map
        num_offsets, c_in, c_out = weight.shape
        grad_out = grad_out.contiguous()
        grad_feats = grad_weight = None
        if ctx.needs_input_grad[1]:
            grad_weight = neighbour_weight_grad(feats, kernel_map.neighbours, grad_out).view(num_offsets, c_in, c_out)
        if ctx.needs_input_grad[0]:
            if kernel_map.identity_offset is not None:
                # Submanifold: input j feeds output nbr[j, K-1-k] through offset k, so block k' of the
                # gathered gradient meets weight[K-1-k'].
                weight_t = weight.flip(0).transpose(1, 2).reshape(num_offsets * c_out, c_in)
                grad_feats = neighbour_gemm(grad_out, kernel_map.neighbours, weight_t)
            else:
                grad_feats = pick_products(grad_out, weight.transpose(1, 2), kernel_map.parent_slots)
        return grad_feats, grad_weight, None


class _PickProducts(torch.autograd.Function):
    """Transposed (up-sampling) conv over a down-sampling map: every fine voxel reads its one coarse parent,
    so `out = pick_products(feats, weight, parent_slots)`: one GEMM and a gather, no scatter.

    Executes N_coarse x K x C_in x C_out MACs (products for absent children are computed and dropped).
    """

    @staticmethod
    def forward(ctx, feats, weight, kernel_map):  # noqa: D102
        ctx.save_for_backward(feats, weight)
        ctx.kernel_map = kernel_map
        return pick_products(feats, weight, kernel_map.parent_slots)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        feats, weight = ctx.saved_tensors
        neighbours = ctx.kernel_map.neighbours  # (N_coarse, K): the gradient of the products is a gather
        num_offsets, c_in, c_out = weight.shape
        grad_out = grad_out.contiguous()
        grad_feats = grad_weight = None
        if ctx.needs_input_grad[0]:
            grad_feats = neighbour_gemm(grad_out, neighbours, weight.transpose(1, 2).reshape(num_offsets * c_out, c_in))
        if ctx.needs_input_grad[1]:
            grad_t = neighbour_weight_grad(grad_out, neighbours, feats)  # (K * C_out, C_in)
            grad_weight = grad_t.view(num_offsets, c_out, c_in).transpose(1, 2)
        return grad_feats, grad_weight, None


class _CompiledConv(torch.autograd.Function):
    """A sparse conv by the compiled engine over a kernel map, exact MACs, either way round:

    - gathering (submanifold or down-sampling conv; `transposed` False): `compiled.neighbour_conv`, on features
      in coordinate order (`KernelMap.in_coordinate_order`: permuted in and out where the rows are not).
      Backward: the weight gradient per offset (`compiled.neighbour_weight_grad`); the input gradient through
      the map's transpose: a submanifold map is its own transpose with offsets mirrored (`k <-> K-1-k`), and
      a down-sampling map gives each input exactly one (output, offset) slot (`compiled.scatter_conv`).
    - scattering (the transposed, up-sampling conv over a down-sampling map; `transposed` True): every fine
      voxel is written once from its coarse parent (`compiled.scatter_conv`); the backward gathers.
    """

    @staticmethod
    def forward(ctx, feats, weight, kernel_map, transposed):  # noqa: D102
        ctx.kernel_map, ctx.transposed = kernel_map, transposed
        if transposed:
            ctx.save_for_backward(feats, weight)
            return compiled.scatter_conv(feats, kernel_map.neighbours, weight, kernel_map.num_in)
        neighbours, order = kernel_map.in_coordinate_order
        if order is not None:
            feats = feats.index_select(0, order)
        ctx.save_for_backward(feats, weight)  # in coordinate order
        return _rows_back(compiled.neighbour_conv(feats, neighbours, weight), order)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):  # noqa: D102
        feats, weight = ctx.saved_tensors
        kernel_map = ctx.kernel_map
        need_feats, need_weight = ctx.needs_input_grad[:2]
        grad_feats = grad_weight = None
        if ctx.transposed:  # neighbours (N_coarse, K) are fine rows
            neighbours = kernel_map.neighbours
            if need_feats:
                grad_feats = compiled.neighbour_conv(grad_out, neighbours, weight.transpose(1, 2))
            if need_weight:
                grad_weight = compiled.neighbour_weight_grad(grad_out, neighbours, feats).transpose(1, 2)
            return grad_feats, grad_weight, None, None
        neighbours, order = kernel_map.in_coordinate_order
        if order is not None:
            grad_out = grad_out.index_select(0, order)
        if need_weight:
            grad_weight = compiled.neighbour_weight_grad(feats, neighbours, grad_out)
        if need_feats:
            weight_t = weight.transpose(1, 2)  # (K, C_out, C_in)
            if kernel_map.identity_offset is not None:
                grad_feats = _rows_back(compiled.neighbour_conv(grad_out, neighbours, weight_t.flip(0)), order)
            else:
                grad_feats = compiled.scatter_conv(grad_out, neighbours, weight_t, kernel_map.num_in)
        return grad_feats, grad_weight, None, None


def _rows_back(rows: Tensor, order: Tensor | None) -> Tensor:
    """Rows computed in coordinate order (`order[i]` is the original row of row i) back in the original order."""
    if order is None:
        return rows
    return torch.empty_like(rows).index_copy_(0, order, rows)


def compiled_applies(kernel_map: KernelMap, feats: Tensor, weight: Tensor) -> bool:
    """Whether the compiled engine runs this conv (see `compiled.use_compiled`): its kernels take a submanifold
    map (stride 1 with the identity offset) or a down-sampling map (stride = kernel size)."""
    supported = kernel_map.identity_offset is not None or kernel_map.stride == kernel_map.kernel_size > 1
    return supported and compiled.use_compiled(feats, weight)
