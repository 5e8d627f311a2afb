"""The fused inference form of MinkUNet (models.segmenter.fused) against the eager model: the same logits (to float
rounding), labels and MACs, on the compiled and the reference engine; the compiled epilogue against PyTorch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.checkpoint import load_checkpoint
from models.compute import MacRecorder
from models.registry import create_model
from models.segmenter.fused import FusedMinkUNet, fusable
from models.sparse import SparseTensor, compiled
from radar.region_growing import RegionGrowingConfig, grow_regions
from radar.roi import roi_points
from radar.simulate import simulate_sequence

REPO_CHECKPOINTS = ("checkpoints/segmenter.pt", "checkpoints/segmenter-slimmed.pt")


@pytest.fixture(scope="module")
def roi():
    """(coords (N, 4), feats (N, 4)) of a region-grown ROI around every object of a simulated frame."""
    frame = list(simulate_sequence("small", 2, seed=8))[1]
    log_power = frame.log_power()
    seeds = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels])
    regions = grow_regions(log_power, seeds, frame.profile, RegionGrowingConfig.for_profile("small"))
    points = roi_points(regions.voxels, log_power, frame.profile, mean_db=60.0, std_db=8.0)
    coords = torch.from_numpy(points.coords)
    return torch.cat([torch.zeros(len(coords), 1, dtype=torch.int64), coords], 1), torch.from_numpy(points.features)


def _trained_like(model: torch.nn.Module) -> torch.nn.Module:
    """Random BatchNorm statistics and affine parameters, so that folding them matters."""
    generator = torch.Generator().manual_seed(0)
    for module in model.modules():
        if isinstance(module, torch.nn.BatchNorm1d):
            n = module.num_features
            module.running_mean.copy_(torch.randn(n, generator=generator) * 0.3)
            module.running_var.copy_(torch.rand(n, generator=generator) + 0.5)
            module.weight.data.copy_(torch.rand(n, generator=generator) + 0.5)
            module.bias.data.copy_(torch.randn(n, generator=generator) * 0.2)
    return model.eval()


def _eager(model, coords, feats):
    with torch.no_grad(), MacRecorder(model) as recorder:
        logits = model(SparseTensor(coords, feats))
    report = recorder.report()
    return logits, report.macs, report.executed


@pytest.mark.parametrize("engine", ["compiled", "reference"])
def test_fused_equals_eager(roi, engine):
    if engine == "compiled" and not compiled.available():
        pytest.skip("the compiled engine did not build here")
    coords, feats = roi
    torch.manual_seed(1)
    model = _trained_like(create_model("minkunet_tiny", preset="small"))
    with compiled.using_kernels(engine):
        logits, macs, executed = _eager(model, coords, feats)
        fused_logits, tally = FusedMinkUNet(model)(SparseTensor(coords, feats))
    torch.testing.assert_close(fused_logits, logits, rtol=1e-4, atol=1e-4)
    assert torch.equal(fused_logits.argmax(1), logits.argmax(1))
    assert (tally.useful, tally.executed) == (macs, executed)


@pytest.mark.parametrize("path", REPO_CHECKPOINTS)
def test_the_shipped_segmenters_fuse_to_the_same_labels(roi, path):
    model = load_checkpoint(path).build().eval()
    assert fusable(model)
    coords, feats = roi
    logits, macs, _ = _eager(model, coords, feats)
    fused_logits, tally = FusedMinkUNet(model)(SparseTensor(coords, feats))
    assert (fused_logits - logits).abs().max() < 1e-3
    assert torch.equal(fused_logits.argmax(1), logits.argmax(1)) and tally.useful == macs


def test_what_cannot_be_fused_is_refused():
    model = create_model("minkunet_tiny", preset="small")
    with pytest.raises(ValueError, match="eval mode"):
        FusedMinkUNet(model.train())
    spvcnn = create_model("spvcnn_tiny", preset="small").eval()
    assert not fusable(spvcnn)
    with pytest.raises(TypeError, match="MinkUNet"):
        FusedMinkUNet(spvcnn)


@pytest.mark.skipif(not compiled.available(), reason="the compiled engine did not build here")
def test_the_compiled_epilogue_equals_pytorch():
    generator = torch.Generator().manual_seed(2)
    src = torch.randn(300, 8, generator=generator)
    neighbours = torch.randint(0, 301, (280, 27), generator=generator)  # 300 = missing
    weight = torch.randn(27, 8, 24, generator=generator)
    bias, residual = torch.randn(24, generator=generator), torch.randn(280, 24, generator=generator)
    plain = compiled.neighbour_conv(src, neighbours, weight)
    torch.testing.assert_close(compiled.neighbour_conv_fused(src, neighbours, weight, bias, residual, True),
                               torch.relu(plain + bias + residual))
    torch.testing.assert_close(compiled.neighbour_conv_fused(src, neighbours, weight), plain)
    # a down-sampling map read backwards: every output row reached at most once; rows never reached get max(bias, 0)
    children = torch.randperm(400, generator=generator)[:320].reshape(40, 8)
    children[::3, 5] = 400
    coarse = torch.randn(40, 8, generator=generator)
    up_weight, up_bias = torch.randn(8, 8, 16, generator=generator), torch.randn(16, generator=generator)
    expected = torch.relu(compiled.scatter_conv(coarse, children, up_weight, 400) + up_bias)
    torch.testing.assert_close(compiled.scatter_conv_fused(coarse, children, up_weight, 400, up_bias, True), expected)
    with pytest.raises(RuntimeError, match="bias"):
        compiled.neighbour_conv_fused(src, neighbours, weight, torch.randn(5))
