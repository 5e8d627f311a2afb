"""Training targets of the centre detector, built from object centres in (fractional) bins.

Target format (what :meth:`CentreNetHead.compute_loss` reads), for a batch of ``B`` frames on the
output grid ``(H, W) = (ceil(R / S), ceil(A / S))`` with output stride ``S`` and at most ``K`` objects
per frame:

- ``heatmap``: float32 ``(B, C, H, W)``, 1 at each object's centre cell, a Gaussian around it (radius
  1 cell, sigma 1/3 cell along range and 1/2 cell along angle, docs/design.md section 5), the maximum where
  objects overlap, 0 elsewhere; ``C = 1`` (one heatmap for every class) or one channel per foreground
  class (an object drawn only in its class's channel, CenterNet's form);
- ``indices``: int64 ``(B, K)``, flat index ``row * W + col`` of each object's centre cell on the grid;
- ``offsets``: float32 ``(B, K, 2)``, sub-cell offset (range, angle) in cells, in ``[0, 1)``: the
  centre in bins is ``(cell + offset) * S``;
- ``doppler``: float32 ``(B, K)``, the object's mean Doppler bin (fractional, ``[0, D)``);
- ``mask``: bool ``(B, K)``, True for the slots holding an object (the others are zero padding).

A centre cell is ``floor(bin / S)`` (output cell ``i`` is centred on input bin ``i * S``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NotRequired, TypedDict

import numpy as np
import torch

from radar.centres import MAX_OBJECTS

OUTPUT_STRIDE = 4
GAUSSIAN_RADIUS = 1  # cells
GAUSSIAN_SIGMA = (1 / 3, 1 / 2)  # cells, (range, angle)


class CentreTargets(TypedDict):
    heatmap: torch.Tensor  # (B, C, H, W) float32, C = 1 or one channel per foreground class
    indices: torch.Tensor  # (B, K) int64
    offsets: torch.Tensor  # (B, K, 2) float32, (range, angle) in cells
    doppler: torch.Tensor  # (B, K) float32, Doppler bins
    mask: torch.Tensor  # (B, K) bool
    peak_weight: NotRequired[torch.Tensor]  # (B, C, H, W) float32: the focal loss's weight at each object's centre


def output_grid(grid_shape: tuple[int, int], output_stride: int = OUTPUT_STRIDE) -> tuple[int, int]:
    """Output grid ``(ceil(R / S), ceil(A / S))`` of an RA grid ``(R, A)``."""
    n_range, n_angle = grid_shape
    return -(-n_range // output_stride), -(-n_angle // output_stride)


def _as_centres(centres: np.ndarray | Sequence) -> np.ndarray:
    array = np.asarray(centres, dtype=np.float64)
    if array.size == 0:
        return np.zeros((0, 3))
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(
            f"centres must be (N, 3) (range bin, angle bin, Doppler bin), got shape {array.shape}"
        )
    if not np.all(np.isfinite(array)):
        raise ValueError("centres must be finite (drop NaN padding before building targets)")
    return array


def _centre_cells(
    centres: np.ndarray, grid_shape: tuple[int, int], output_stride: int
) -> tuple[np.ndarray, np.ndarray]:
    """Integer centre cells (N, 2) and sub-cell offsets (N, 2) of centres (N, 3) in bins."""
    scaled = centres[:, :2] / output_stride
    cells = np.floor(scaled).astype(np.int64)
    height, width = output_grid(grid_shape, output_stride)
    outside = (cells[:, 0] < 0) | (cells[:, 0] >= height) | (cells[:, 1] < 0) | (cells[:, 1] >= width)
    if np.any(outside):
        raise ValueError(
            f"centre(s) {centres[outside, :2].tolist()} (range, angle bins) fall outside the "
            f"{grid_shape[0]} x {grid_shape[1]} RA grid"
        )
    return cells, scaled - cells


def render_heatmap(
    centres: np.ndarray | Sequence,
    grid_shape: tuple[int, int],
    *,
    output_stride: int = OUTPUT_STRIDE,
    sigma: tuple[float, float] = GAUSSIAN_SIGMA,
    radius: int = GAUSSIAN_RADIUS,
) -> np.ndarray:
    """Centre heatmap ``(ceil(R/S), ceil(A/S))`` float32 of one frame.

    ``centres``: ``(N, 3)`` fractional (range bin, angle bin, Doppler bin) on the ``(R, A)`` grid
    ``grid_shape``; the Doppler column is ignored here. Each object adds
    ``exp(-(dr^2 / (2 sigma_r^2) + da^2 / (2 sigma_a^2)))`` for integer cell offsets ``|dr|, |da| <=
    radius`` around its centre cell (peak exactly 1); overlaps take the maximum.
    """
    centres = _as_centres(centres)
    height, width = output_grid(grid_shape, output_stride)
    heatmap = np.zeros((height, width), dtype=np.float32)
    if len(centres) == 0:
        return heatmap
    cells, _ = _centre_cells(centres, grid_shape, output_stride)
    steps = np.arange(-radius, radius + 1)
    kernel = np.exp(
        -(steps[:, None] ** 2 / (2 * sigma[0] ** 2) + steps[None, :] ** 2 / (2 * sigma[1] ** 2))
    ).astype(np.float32)  # (2 radius + 1, 2 radius + 1), 1 at the centre
    for row, col in cells:
        r0, r1 = max(0, row - radius), min(height, row + radius + 1)
        c0, c1 = max(0, col - radius), min(width, col + radius + 1)
        patch = kernel[r0 - row + radius : r1 - row + radius, c0 - col + radius : c1 - col + radius]
        np.maximum(heatmap[r0:r1, c0:c1], patch, out=heatmap[r0:r1, c0:c1])
    return heatmap


def build_centre_targets(
    batch_centres: Sequence[np.ndarray | Sequence],
    grid_shape: tuple[int, int],
    *,
    output_stride: int = OUTPUT_STRIDE,
    max_objects: int = MAX_OBJECTS,
    sigma: tuple[float, float] = GAUSSIAN_SIGMA,
    radius: int = GAUSSIAN_RADIUS,
    centre_weights: Sequence[np.ndarray] | None = None,
    heatmap_classes: int = 1,
    classes: Sequence[np.ndarray] | None = None,
) -> CentreTargets:
    """Targets of a batch (format in the module docstring) from per-frame centres.

    ``heatmap_classes > 1``: one heatmap channel per foreground class; ``classes[b]`` (``(N_b,)``, 0-based
    foreground class, i.e. the store's class id - 1) says in which channel each object of frame ``b`` is drawn.

    ``centre_weights[b]`` (optional, ``(N_b,)``): the focal loss's weight at each object's centre cell
    (``peak_weight``; 1 elsewhere), e.g. a weight per class so that a weak class's peaks count more.

    ``batch_centres[b]``: ``(N_b, 3)`` fractional (range bin, angle bin, Doppler bin) of frame ``b``'s
    objects on the ``(R, A)`` grid ``grid_shape``. Raises ``ValueError`` when a frame has more than
    ``max_objects`` objects or a centre lies outside the grid.
    """
    if output_stride < 1:
        raise ValueError(f"output_stride must be >= 1, got {output_stride}")
    if max_objects < 1:
        raise ValueError(f"max_objects must be >= 1, got {max_objects}")
    if heatmap_classes < 1:
        raise ValueError(f"heatmap_classes must be >= 1, got {heatmap_classes}")
    if heatmap_classes > 1 and classes is None:
        raise ValueError(f"heatmap_classes={heatmap_classes} needs a class per object (classes), got None")
    height, width = output_grid(grid_shape, output_stride)
    batch = len(batch_centres)
    heatmap = np.zeros((batch, heatmap_classes, height, width), dtype=np.float32)
    indices = np.zeros((batch, max_objects), dtype=np.int64)
    offsets = np.zeros((batch, max_objects, 2), dtype=np.float32)
    doppler = np.zeros((batch, max_objects), dtype=np.float32)
    mask = np.zeros((batch, max_objects), dtype=bool)
    for b, frame_centres in enumerate(batch_centres):
        centres = _as_centres(frame_centres)
        if len(centres) > max_objects:
            raise ValueError(f"frame {b} has {len(centres)} objects, more than max_objects={max_objects}")
        if heatmap_classes == 1:
            heatmap[b, 0] = render_heatmap(centres, grid_shape, output_stride=output_stride, sigma=sigma, radius=radius)
        else:
            frame_classes = np.asarray(classes[b], np.int64)[: len(centres)]
            if len(frame_classes) != len(centres) or np.any((frame_classes < 0) | (frame_classes >= heatmap_classes)):
                raise ValueError(f"frame {b}: classes must be {len(centres)} values in [0, {heatmap_classes}), "
                                 f"got {frame_classes.tolist()}")
            for c in np.unique(frame_classes):
                heatmap[b, c] = render_heatmap(centres[frame_classes == c], grid_shape, output_stride=output_stride,
                                               sigma=sigma, radius=radius)
        if len(centres) == 0:
            continue
        cells, sub_cell = _centre_cells(centres, grid_shape, output_stride)
        n = len(centres)
        indices[b, :n] = cells[:, 0] * width + cells[:, 1]
        offsets[b, :n] = sub_cell
        doppler[b, :n] = centres[:, 2]
        mask[b, :n] = True
    targets = CentreTargets(
        heatmap=torch.from_numpy(heatmap),
        indices=torch.from_numpy(indices),
        offsets=torch.from_numpy(offsets),
        doppler=torch.from_numpy(doppler),
        mask=torch.from_numpy(mask),
    )
    if centre_weights is not None:
        weight = np.ones((batch, heatmap_classes, height * width), np.float32)
        for b, frame_weights in enumerate(centre_weights):
            n = int(mask[b].sum())
            weight[b][:, indices[b, :n]] = np.asarray(frame_weights, np.float32)[:n]
        targets["peak_weight"] = torch.from_numpy(weight.reshape(batch, heatmap_classes, height, width))
    return targets


def crop_centre_targets(targets: CentreTargets, origins: Sequence[tuple[int, int]], window_cells: tuple[int, int],
                        ) -> CentreTargets:
    """The targets of range x angle windows of the frames, cut from the whole frames' ``targets``.

    ``origins[b]``: the window's first (range, angle) output cell in frame ``b``; ``window_cells``: its size
    ``(h, w)`` in cells. The heatmap (and ``peak_weight``) is that window of the whole frame's, so a Gaussian of
    an object just outside the window reaches in as it does on the whole frame; an object keeps its slot, offset
    and Doppler when its centre cell lies inside the window (its index then counts on the ``w``-wide window
    grid) and is masked out otherwise. A window of the whole grid returns the targets unchanged.
    """
    heatmap = targets["heatmap"]
    batch, _, height, width = heatmap.shape
    h, w = window_cells
    if len(origins) != batch:
        raise ValueError(f"one origin per frame: {batch} frames, got {len(origins)} origins")
    for row, col in origins:
        if not (0 <= row <= height - h and 0 <= col <= width - w):
            raise ValueError(f"window at cell ({row}, {col}) of {h} x {w} cells does not fit the {height} x "
                             f"{width} grid")
    rows = targets["indices"] // width
    cols = targets["indices"] % width
    start = torch.as_tensor(origins, dtype=torch.int64).reshape(batch, 1, 2)
    inside = ((rows >= start[..., 0]) & (rows < start[..., 0] + h) & (cols >= start[..., 1])
              & (cols < start[..., 1] + w))
    mask = targets["mask"] & inside
    indices = torch.where(mask, (rows - start[..., 0]) * w + (cols - start[..., 1]), 0)
    cropped = CentreTargets(
        heatmap=torch.stack([heatmap[b, :, r:r + h, c:c + w] for b, (r, c) in enumerate(origins)]),
        indices=indices,
        offsets=torch.where(mask[..., None], targets["offsets"], 0.0),
        doppler=torch.where(mask, targets["doppler"], 0.0),
        mask=mask,
    )
    if "peak_weight" in targets:
        cropped["peak_weight"] = torch.stack([targets["peak_weight"][b, :, r:r + h, c:c + w]
                                              for b, (r, c) in enumerate(origins)])
    return cropped
