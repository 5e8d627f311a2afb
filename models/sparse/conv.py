"""Sparse convolution layers over kernel maps. How each call runs (the compiled engine, or one of the reference
engine's two paths) is `models.sparse.paths`; the autograd Functions are `models.sparse.functions`.

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

from models.sparse.paths import apply_kernel_map
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
