"""MinkUNet and SPVCNN: size, per-voxel outputs, batch separation, MAC counts, point branch, training."""

from __future__ import annotations

import pytest
import torch
from torch.utils.flop_counter import FlopCounterMode

from models.segmenter.minkunet import BASE_WIDTHS, MinkUNet, scaled_widths
from models.segmenter.spvcnn import SPVCNN, PointTensor, devoxelize, voxelize
from models.sparse import SparseTensor, compiled, last_forward_executed_macs, last_forward_macs


def random_cloud(seed: int, *, num_voxels: int, extent: int, batch_size: int = 1) -> SparseTensor:
    """Unique random voxels (N, 4) in [0, extent)^3 per sample with 4 features
    (normalised x, y, z and noise, like the ROI features x, y, velocity, log power)."""
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for batch in range(batch_size):
        flat = torch.randperm(extent**3, generator=generator)[:num_voxels]
        xyz = torch.stack([flat // extent**2, (flat // extent) % extent, flat % extent], dim=1)
        rows.append(torch.cat([torch.full((num_voxels, 1), batch), xyz], dim=1))
    coords = torch.cat(rows)
    feats = torch.cat([coords[:, 1:] / extent, torch.randn(len(coords), 1, generator=generator)], dim=1)
    return SparseTensor(coords, feats.float())


def num_params(model: torch.nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def test_minkunet_ratio_037_has_the_papers_size():
    model = MinkUNet.from_ratio(0.37, in_channels=4, num_classes=5)
    assert model.config["widths"] == [int(w * 0.37) for w in BASE_WIDTHS]
    assert abs(num_params(model) - 2.92e6) / 2.92e6 < 0.005  # MinkUNet at ratio 1: 2.92 M (paper 2.93 M)
    assert num_params(MinkUNet.from_ratio(0.74)) > 3 * num_params(model)  # widths scale the size


def test_bad_widths_are_rejected():
    with pytest.raises(ValueError, match="9 positive"):
        MinkUNet(in_channels=4, num_classes=5, widths=(8, 8, 8))
    with pytest.raises(ValueError, match="ratio"):
        scaled_widths(0.0)


def test_minkunet_labels_each_voxel_in_input_order_and_keeps_samples_apart():
    model = MinkUNet.from_ratio(0.1, in_channels=4, num_classes=3).eval()
    both = random_cloud(0, num_voxels=300, extent=12, batch_size=2)
    with torch.no_grad():
        logits = model(both)
        assert logits.shape == (600, 3)
        permutation = torch.randperm(600, generator=torch.Generator().manual_seed(1))
        permuted = model(SparseTensor(both.coords[permutation], both.feats[permutation]))
        torch.testing.assert_close(permuted, logits[permutation])
        # Sample 1 alone (as batch 0) must get the same logits as inside the batch.
        second = both.coords[:, 0] == 1
        alone_coords = both.coords[second].clone()
        alone_coords[:, 0] = 0
        alone = model(SparseTensor(alone_coords, both.feats[second]))
    torch.testing.assert_close(alone, logits[second])


@pytest.mark.parametrize("path", ["per_offset", "gemm"])
@pytest.mark.parametrize("architecture", ["minkunet", "spvcnn"])
def test_mac_count_matches_flop_counter(architecture, path):
    """Executed MACs are what the kernels ran (FlopCounterMode counts matrix products); useful MACs equal
    them on the per-offset path and are fewer on the GEMM path (missing neighbours multiply zeros)."""
    cloud = random_cloud(2, num_voxels=400, extent=14, batch_size=2)
    if architecture == "minkunet":
        model, inputs = MinkUNet.from_ratio(0.2, in_channels=4, num_classes=5), cloud
    else:
        model = SPVCNN.from_ratio(0.2, in_channels=4, num_classes=5)
        inputs = PointTensor(cloud.coords[:, 0].clone(), cloud.coords[:, 1:] + 0.5, cloud.feats)
    for module in model.modules():
        if hasattr(module, "path"):
            module.path = path
    # The pure-PyTorch engine's paths (FlopCounterMode sees its matrix products, not the compiled kernels).
    with compiled.using_kernels("reference"), FlopCounterMode(display=False) as counter, torch.no_grad():
        model(inputs)
    assert last_forward_macs(model) > 0
    assert last_forward_executed_macs(model) * 2 == counter.get_total_flops()
    if path == "per_offset":
        assert last_forward_macs(model) == last_forward_executed_macs(model)
    else:
        assert last_forward_macs(model) < last_forward_executed_macs(model)


def test_voxelize_averages_and_devoxelize_interpolates_trilinearly():
    generator = torch.Generator().manual_seed(3)
    # A full 6^3 block of voxels whose feature is a linear function of the voxel centre: trilinear
    # interpolation must reproduce the function exactly at points between the inner voxel centres.
    grid = torch.stack(torch.meshgrid(*[torch.arange(6)] * 3, indexing="ij"), dim=-1).reshape(-1, 3)
    centres = grid + 0.5
    slope = torch.tensor([[0.7], [-1.3], [2.0]])
    voxel_points = PointTensor(torch.zeros(len(grid), dtype=torch.int64), centres, centres @ slope)
    voxels = voxelize(voxel_points)
    queries = 1.0 + 4.0 * torch.rand(50, 3, generator=generator)  # within [0.5, 5.5] in every axis
    query_points = PointTensor(torch.zeros(50, dtype=torch.int64), queries, torch.zeros(50, 1))
    torch.testing.assert_close(devoxelize(voxels, query_points), queries @ slope)

    # Two points in one voxel and one alone: the voxel feature is their mean.
    points = PointTensor(
        torch.tensor([0, 0, 1]),
        torch.tensor([[0.2, 0.3, 0.4], [0.9, 0.1, 0.5], [0.2, 0.3, 0.4]]),
        torch.tensor([[1.0], [3.0], [5.0]]),
    )
    pooled = voxelize(points)
    assert pooled.coords.tolist() == [[0, 0, 0, 0], [1, 0, 0, 0]]
    assert pooled.feats.squeeze(1).tolist() == [2.0, 5.0]


def test_spvcnn_forward_backward_on_a_tiny_cloud():
    cloud = random_cloud(4, num_voxels=250, extent=10, batch_size=2)
    generator = torch.Generator().manual_seed(5)
    # Several points per voxel at random positions inside it.
    coords = torch.cat([cloud.coords[:, 1:] + torch.rand(500, 3, generator=generator)] * 2)
    points = PointTensor(torch.cat([cloud.coords[:, 0]] * 2), coords, torch.cat([cloud.feats] * 2))
    model = SPVCNN.from_ratio(0.1, in_channels=4, num_classes=4)
    logits = model(points)
    assert logits.shape == (1000, 4)
    torch.nn.functional.cross_entropy(logits, torch.randint(0, 4, (1000,), generator=generator)).backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad).all(), name
    assert any(p.grad.abs().sum() > 0 for p in model.point_mlps.parameters())


@pytest.mark.parametrize("architecture", ["minkunet", "spvcnn"])
def test_loss_falls_when_overfitting_a_tiny_example(architecture):
    torch.manual_seed(0)
    cloud = random_cloud(6, num_voxels=300, extent=10, batch_size=2)
    # Labels from position (blocks of 4 voxels), so the network has to use its spatial context.
    labels = ((cloud.coords[:, 1] // 4 + cloud.coords[:, 2] // 4) % 3).long()
    if architecture == "minkunet":
        model, inputs = MinkUNet.from_ratio(0.25, in_channels=4, num_classes=3), cloud
    else:
        model = SPVCNN.from_ratio(0.25, in_channels=4, num_classes=3)
        inputs = PointTensor(cloud.coords[:, 0].clone(), cloud.coords[:, 1:] + 0.5, cloud.feats)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(25):
        optimizer.zero_grad()
        loss = torch.nn.functional.cross_entropy(model(inputs), labels)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0]
    with torch.no_grad():  # still in train mode: BN running statistics lag after 25 steps
        accuracy = (model(inputs).argmax(dim=1) == labels).float().mean().item()
    assert accuracy > 0.95


def test_empty_input_gives_empty_logits_in_eval_mode():
    """A frame without detections has no ROI voxels; inference must not fail on it."""
    with torch.no_grad():
        voxels = SparseTensor(torch.zeros(0, 4, dtype=torch.int64), torch.zeros(0, 4))
        assert MinkUNet.from_ratio(0.1, num_classes=3).eval()(voxels).shape == (0, 3)
        points = PointTensor(torch.zeros(0, dtype=torch.int64), torch.zeros(0, 3), torch.zeros(0, 4))
        assert SPVCNN.from_ratio(0.1, num_classes=3).eval()(points).shape == (0, 3)
