"""Sparse convolution layers over kernel maps, by one of two engines (`models.sparse.native`: setting
`RADARSEG_SPARSE_ENGINE`): the compiled kernels (CPU, float32), or pure PyTorch, the reference, by one of
two paths chosen per layer (`choose_path`): an implicit GEMM over the neighbour table in cache-sized
chunks, or gather / matmul / scatter-add per kernel offset.

Every conv holds a weight `[K, C_in, C_out]` (K = kernel voxels) and records the exact multiply-
accumulates of its last call in `last_macs` (sum over offsets of pairs x C_in x C_out) and those its
kernels executed in `last_executed_macs`; `last_forward_macs` / `last_forward_executed_macs` add them up over a model
after a forward pass. The code is device-agnostic: it runs wherever the
features and coordinates live.

Equivalences with dense PyTorch on a grid whose origin is coordinate 0 (tested):
`SubmanifoldConv3d` = `F.conv3d(padding=k//2)` read at the input voxels; `StridedConv3d` =
`F.conv3d(kernel 2, stride 2)` read at `unique(floor(coords / 2))`; `TransposedConv3d` =
`F.conv_transpose3d(kernel 2, stride 2)` read at the finer voxels; dense weight `[C_out, C_in, k, k, k]`
(transposed: `[C_in, C_out, k, k, k]`) flattened over `(k, k, k)` is our `K` axis.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from models.sparse import native
from models.sparse.kernel_map import KernelMap
from models.sparse.tensor import SparseTensor


class MACCounted(nn.Module):
    """A layer that records its multiply-accumulates of the last forward call: `last_macs` the useful ones
    (pairs x C_in x C_out), `last_executed_macs` those its kernels actually ran (more on the GEMM path,
    which also multiplies the zeros of missing neighbours)."""

    last_macs: int = 0
    last_executed_macs: int = 0


def last_forward_macs(model: nn.Module) -> int:
    """Sum of `last_macs` over all MAC-counting layers of a model (call after a forward pass).

    Layers that did not run in the last forward keep their previous value; a layer called twice in one
    forward counts only its last call.
    """
    return sum(module.last_macs for module in model.modules() if isinstance(module, MACCounted))


def last_forward_executed_macs(model: nn.Module) -> int:
    """Sum of `last_executed_macs` over a model (call after a forward pass): what the kernels ran."""
    return sum(module.last_executed_macs for module in model.modules() if isinstance(module, MACCounted))


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


class _NativeConv(torch.autograd.Function):
    """A sparse conv by the compiled engine over a kernel map, exact MACs, either way round:

    - gathering (submanifold or down-sampling conv; `transposed` False): `native.neighbour_conv`, on features
      in coordinate order (`KernelMap.in_coordinate_order`: permuted in and out where the rows are not).
      Backward: the weight gradient per offset (`native.neighbour_weight_grad`); the input gradient through
      the map's transpose: a submanifold map is its own transpose with offsets mirrored (`k <-> K-1-k`), and
      a down-sampling map gives each input exactly one (output, offset) slot (`native.scatter_conv`).
    - scattering (the transposed, up-sampling conv over a down-sampling map; `transposed` True): every fine
      voxel is written once from its coarse parent (`native.scatter_conv`); the backward gathers.
    """

    @staticmethod
    def forward(ctx, feats, weight, kernel_map, transposed):  # noqa: D102
        ctx.kernel_map, ctx.transposed = kernel_map, transposed
        if transposed:
            ctx.save_for_backward(feats, weight)
            return native.scatter_conv(feats, kernel_map.neighbours, weight, kernel_map.num_in)
        neighbours, order = kernel_map.in_coordinate_order
        if order is not None:
            feats = feats.index_select(0, order)
        ctx.save_for_backward(feats, weight)  # in coordinate order
        return _rows_back(native.neighbour_conv(feats, neighbours, weight), order)

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
                grad_feats = native.neighbour_conv(grad_out, neighbours, weight.transpose(1, 2))
            if need_weight:
                grad_weight = native.neighbour_weight_grad(grad_out, neighbours, feats).transpose(1, 2)
            return grad_feats, grad_weight, None, None
        neighbours, order = kernel_map.in_coordinate_order
        if order is not None:
            grad_out = grad_out.index_select(0, order)
        if need_weight:
            grad_weight = native.neighbour_weight_grad(feats, neighbours, grad_out)
        if need_feats:
            weight_t = weight.transpose(1, 2)  # (K, C_out, C_in)
            if kernel_map.identity_offset is not None:
                grad_feats = _rows_back(native.neighbour_conv(grad_out, neighbours, weight_t.flip(0)), order)
            else:
                grad_feats = native.scatter_conv(grad_out, neighbours, weight_t, kernel_map.num_in)
        return grad_feats, grad_weight, None, None


def _rows_back(rows: Tensor, order: Tensor | None) -> Tensor:
    """Rows computed in coordinate order (`order[i]` is the original row of row i) back in the original order."""
    if order is None:
        return rows
    return torch.empty_like(rows).index_copy_(0, order, rows)


def native_applies(kernel_map: KernelMap, feats: Tensor, weight: Tensor) -> bool:
    """Whether the compiled engine runs this conv (see `native.use_native`): its kernels take a submanifold
    map (stride 1 with the identity offset) or a down-sampling map (stride = kernel size)."""
    supported = kernel_map.identity_offset is not None or kernel_map.stride == kernel_map.kernel_size > 1
    return supported and native.use_native(feats, weight)


PATHS = ("per_offset", "gemm")
"""How a conv runs over its map: gather / matmul / scatter per offset (`per_offset`, executes exactly the
useful MACs), or all offsets in one matrix product (`gemm`: `_NeighbourGemm`, or `_PickProducts` for a
transposed conv, which also multiplies the missing neighbours)."""


GEMM_MIN_FILL = 0.25
"""Smallest fill (pairs / (N_out x K)) at which the GEMM path runs: it executes 1 / fill times the useful
MACs. On uniformly scattered voxels (fill 0.08) the per-offset path wins."""
GEMM_MAX_IN_CHANNELS = 16
"""Widest input of a submanifold (K = 27) or transposed conv run by the GEMM path. 24 and 32 measured in the
second session: training steps at ratio 0.25 within 6 % of 16 (and 64 worse at ratio 0.37), so 16 stays."""

GEMM_WIDE_MIN_FILL = 0.65
GEMM_WIDE_MIN_VOXELS = 16384
"""A submanifold map with at least this fill and this many outputs takes the GEMM path at any width: the
per-offset path's gathers and scatters no longer fit in cache, and the GEMM wastes under 1 / 0.65 - 1 = 54 %."""


def choose_path(kernel_map: KernelMap, in_channels: int, out_channels: int, *, transposed: bool) -> str:
    """The rule measured on the shipped MinkUNet's ROIs (2 x 25k voxels, fill 0.45-0.85 at every stride;
    best of 5 interleaved runs, forward + backward, one thread; `benchmarks/sparse_conv.py`):

    - down-sampling (K = 8): GEMM at every width (0.3-0.7x the per-offset time): 8 offsets make the
      per-offset path pay 24 small operations for about one product per input voxel;
    - up-sampling (transposed, K = 8): GEMM up to 16 input channels, per-offset above (second session,
      thread CPU time, fwd + bwd on the same ROI pair: 24 -> 24 at stride 2 5.3 ms against 8.9, 32 -> 24 at
      stride 4 1.6 against 3.2, 35 -> 35 13.9 against 20.1, 47 -> 35 4.0 against 6.8, equal at 47-94 channels
      on under 1 k voxels): its GEMM multiplies all 8 children of every coarse voxel, about 2.2x the pairs;
    - submanifold (K = 27): GEMM up to 16 input channels (8 -> 8: 0.45-0.8x at strides 1-4), per-offset
      above (32 -> 24 even, 64 -> 64: per-offset 0.8x the GEMM's time): once a chunk's gathered rows are wide
      the GEMM's wasted MACs (1 / fill - 1 per useful one) cost more than the per-offset overhead;
    - except on large, well-filled maps (at least `GEMM_WIDE_MIN_VOXELS` outputs and fill >= `GEMM_WIDE_MIN_FILL`),
      where the GEMM wins at every width (second session, 20 k blob voxels, fill 0.77, fwd + bwd: 32 ch 75 ms
      against 101, 64 ch 256 against 326); on the shipped ROIs (fill 0.5 at strides 1-2, 0.7 on under 4 k
      voxels at strides 4-8) per-offset stays as fast or faster above 16 channels;
    - either, only while fill >= `GEMM_MIN_FILL`.
    """
    # The same fill for a transposed conv: it computes K products per coarse voxel and keeps num_pairs.
    fill = kernel_map.num_pairs / max(1, kernel_map.num_out * kernel_map.num_offsets)
    if fill < GEMM_MIN_FILL:
        return "per_offset"
    if kernel_map.stride == 1 and not transposed and fill >= GEMM_WIDE_MIN_FILL \
            and kernel_map.num_out >= GEMM_WIDE_MIN_VOXELS:
        return "gemm"
    if (kernel_map.stride == 1 or transposed) and in_channels > GEMM_MAX_IN_CHANNELS:
        return "per_offset"
    return "gemm"


def apply_kernel_map(feats: Tensor, weight: Tensor, kernel_map: KernelMap, *, transposed: bool,
                     path: str = "auto") -> tuple[Tensor, int, int]:
    """Run one sparse convolution over a kernel map.

    Args:
        feats: (N_in, C_in) input features (for `transposed`, the coarse side of the map).
        weight: (K, C_in, C_out).
        kernel_map: pairs per offset; `transposed` swaps its input and output roles.
        transposed: run the adjoint (up-sampling) of the map's convolution.
        path: one of `PATHS`, or "auto" for `choose_path`: how the pure-PyTorch engine runs it (the compiled
            engine, where `native_applies`, has one path and ignores this).

    Returns:
        output features (N_out, C_out), the useful MACs (pairs x C_in x C_out) and the executed MACs.
    """
    c_in, c_out = weight.shape[1], weight.shape[2]
    useful = kernel_map.num_pairs * c_in * c_out
    if native_applies(kernel_map, feats, weight):
        out = _NativeConv.apply(feats, weight, kernel_map, transposed)
        return out, useful, useful
    if path == "auto":
        path = choose_path(kernel_map, c_in, c_out, transposed=transposed)
    if path == "gemm":
        if transposed:
            out = _PickProducts.apply(feats, weight, kernel_map)
            return out, useful, kernel_map.num_out * kernel_map.num_offsets * c_in * c_out
        out = _NeighbourGemm.apply(feats, weight, kernel_map)
        return out, useful, kernel_map.num_out * kernel_map.num_offsets * c_in * c_out
    if path != "per_offset":
        raise ValueError(f"path must be one of {PATHS} or 'auto', got {path!r}")
    if transposed:
        sources, targets, num_out = kernel_map.out_indices, kernel_map.in_indices, kernel_map.num_in
    else:
        sources, targets, num_out = kernel_map.in_indices, kernel_map.out_indices, kernel_map.num_out
    out = _GatherMatmulScatter.apply(
        feats, weight, sources, targets, kernel_map.pair_counts, kernel_map.identity_offset, num_out
    )
    return out, useful, useful


class _KernelConv(MACCounted):
    """Shared parameters and initialisation of the kernel convolutions."""

    path: str = "auto"
    """`PATHS` member or "auto" (`choose_path`); a plain attribute, so benchmarks can force a path."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, *, bias: bool) -> None:
        super().__init__()
        if in_channels < 1 or out_channels < 1:
            raise ValueError(f"channel counts must be >= 1, got {in_channels} -> {out_channels}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.weight = nn.Parameter(torch.empty(kernel_size**3, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Uniform init with bound 1 / sqrt(fan_in), fan_in = K x C_in (as a dense Conv3d's bias init)."""
        bound = 1.0 / math.sqrt(self.weight.shape[0] * self.in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def _check(self, x: SparseTensor) -> None:
        if x.num_channels != self.in_channels:
            raise ValueError(f"{type(self).__name__} expects {self.in_channels} input channels, got {x.num_channels}")

    def _finish(self, out: Tensor) -> Tensor:
        return out if self.bias is None else out + self.bias

    def extra_repr(self) -> str:
        has_bias = self.bias is not None
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={has_bias}"


class SubmanifoldConv3d(_KernelConv):
    """k^3 convolution with stride 1 whose output voxels are exactly the input voxels.

    Input (N, C_in) at tensor stride s -> output (N, C_out) at tensor stride s, same coordinates.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, *, bias: bool = False) -> None:
        if kernel_size % 2 != 1:
            raise ValueError(f"kernel_size must be odd, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size, bias=bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check(x)
        kernel_map = x.cache.kernel_map(x.stride, self.kernel_size, 1)
        out, self.last_macs, self.last_executed_macs = apply_kernel_map(
            x.feats, self.weight, kernel_map, transposed=False, path=self.path
        )
        return x.replace_feats(self._finish(out))


class StridedConv3d(_KernelConv):
    """2^3 convolution with stride 2 (down-sampling).

    Input (N, C_in) at tensor stride s -> output (M, C_out) at stride 2s on the voxels
    `unique(floor(coords / 2))`, M <= N.
    """

    def __init__(self, in_channels: int, out_channels: int, *, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 2, bias=bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check(x)
        kernel_map = x.cache.kernel_map(x.stride, 2, 2)
        out, self.last_macs, self.last_executed_macs = apply_kernel_map(
            x.feats, self.weight, kernel_map, transposed=False, path=self.path
        )
        coarse = 2 * x.stride
        return SparseTensor(x.cache.coords(coarse), self._finish(out), coarse, cache=x.cache)


class TransposedConv3d(_KernelConv):
    """2^3 transposed convolution with stride 2 (up-sampling), reusing the strided conv's kernel map.

    Input (M, C_in) at tensor stride 2s -> output (N, C_out) at stride s on the finer voxels this
    tensor was down-sampled from (the same rows as the skip connection at stride s).
    """

    def __init__(self, in_channels: int, out_channels: int, *, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 2, bias=bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        self._check(x)
        if x.stride % 2 != 0:
            raise ValueError(f"cannot up-sample a tensor at odd tensor stride {x.stride}")
        fine = x.stride // 2
        kernel_map = x.cache.kernel_map(fine, 2, 2)
        out, self.last_macs, self.last_executed_macs = apply_kernel_map(
            x.feats, self.weight, kernel_map, transposed=True, path=self.path
        )
        return SparseTensor(x.cache.coords(fine), self._finish(out), fine, cache=x.cache)


class PointwiseConv(MACCounted):
    """1x1 convolution: a linear map of every voxel's (or point's) features.

    Accepts a `SparseTensor` (returns one on the same voxels) or plain features (N, C_in) -> (N, C_out),
    so the point branch of SPVCNN and the classifiers count their MACs the same way.
    """

    def __init__(self, in_channels: int, out_channels: int, *, bias: bool = False) -> None:
        super().__init__()
        self.linear = nn.Linear(in_channels, out_channels, bias=bias)

    @property
    def weight(self) -> Tensor:
        """(C_out, C_in), as `nn.Linear`."""
        return self.linear.weight

    def forward(self, x: SparseTensor | Tensor) -> SparseTensor | Tensor:
        feats = x.feats if isinstance(x, SparseTensor) else x
        out = self.linear(feats)
        self.last_macs = feats.shape[0] * self.linear.in_features * self.linear.out_features
        self.last_executed_macs = self.last_macs
        return x.replace_feats(out) if isinstance(x, SparseTensor) else out


class BatchNorm(nn.BatchNorm1d):
    """BatchNorm over the voxels of a sparse tensor: features (N, C) normalised per channel."""

    def forward(self, x: SparseTensor) -> SparseTensor:  # type: ignore[override]
        return x.replace_feats(super().forward(x.feats))


class ReLU(nn.Module):
    """ReLU on the features of a sparse tensor."""

    def __init__(self, inplace: bool = False) -> None:
        super().__init__()
        self.inplace = inplace

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.replace_feats(torch.relu_(x.feats) if self.inplace else torch.relu(x.feats))
