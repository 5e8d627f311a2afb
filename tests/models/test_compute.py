"""Analytic params/MACs counter against torch's FlopCounterMode (MACs = FLOPs / 2)."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from models.compute import (
    ComputeCounter,
    ComputeReport,
    MacRecorder,
    count_macs,
    count_params,
    dynamic_macs,
)
from models.registry import create_model
from radar.profiles import get_profile


def flop_counter_macs(model: nn.Module, *inputs: torch.Tensor) -> int:
    with FlopCounterMode(display=False) as counter:
        model(*inputs)
    total = counter.get_total_flops()
    assert total % 2 == 0
    return total // 2


@pytest.mark.parametrize(
    ("name", "preset"),
    [("centre_detector_tiny", "small"), ("centre_detector_tiny", "nxp"), ("centre_detector", "small")],
)
def test_detector_macs_equal_flop_counter(name, preset):
    n_range, n_angle, n_doppler = get_profile(preset).shape
    model = create_model(name, preset=preset).eval()
    shape = (2, n_doppler, n_range, n_angle)
    report = count_macs(model, shape)
    with torch.no_grad():
        expected = flop_counter_macs(model, torch.randn(shape))
    assert report.macs == expected
    assert report.macs_paper == report.macs  # no transposed convs in the detector
    assert report.params == sum(p.numel() for p in model.parameters())
    assert sum(report.by_stage.values()) == report.macs
    assert set(report.by_stage) == {"doppler_compress", "backbone", "neck", "head"}


def test_chosen_detector_cost_at_carrada_is_near_the_paper():
    report = count_macs(create_model("centre_detector", preset="carrada"), (1, 64, 256, 256))
    assert report.params == pytest.approx(2.08e6, rel=0.06)
    assert report.macs == pytest.approx(0.49e9, rel=0.06)


LAYERS = [
    (nn.Conv1d(4, 6, 3), (2, 4, 9)),
    (nn.Conv2d(6, 12, 3, stride=2, padding=1, groups=3), (2, 6, 9, 10)),
    (nn.Conv2d(8, 8, 5, padding=2, groups=8), (1, 8, 7, 7)),  # depthwise
    (nn.Conv3d(4, 6, 3, padding=1, groups=2), (1, 4, 5, 6, 7)),
    (nn.Linear(7, 5), (2, 3, 7)),
    (nn.ConvTranspose1d(4, 6, 4, stride=2), (1, 4, 9)),
    (nn.ConvTranspose2d(8, 4, 2, stride=2), (2, 8, 5, 6)),
    (nn.ConvTranspose2d(8, 4, 3, stride=2, padding=1, output_padding=1, groups=2), (2, 8, 5, 6)),
    (nn.ConvTranspose3d(4, 6, 2, stride=2), (1, 4, 3, 3, 3)),
]


@pytest.mark.parametrize(("layer", "shape"), LAYERS, ids=lambda v: type(v).__name__ if isinstance(v, nn.Module) else "")
def test_layer_macs_equal_flop_counter(layer, shape):
    report = count_macs(layer, shape)
    assert report.macs == flop_counter_macs(layer, torch.randn(shape))
    assert report.macs > 0


def test_transposed_conv_paper_convention_overcounts_by_kernel_area():
    layer = nn.ConvTranspose2d(16, 8, (2, 3), stride=(2, 3))  # stride == kernel: the usual upsampling
    report = count_macs(layer, (1, 16, 10, 10))
    assert report.macs == 1 * 16 * 10 * 10 * 8 * 6  # every input position, C_in * C_out * k
    assert report.macs_paper == report.macs * 2 * 3
    assert report.to_dict()["macs_paper_convention"].startswith("transposed convs counted per output")
    # the paper's way for a generic transposed conv: a forward conv at every output position
    odd = nn.ConvTranspose2d(4, 4, 3, stride=2)
    odd_report = count_macs(odd, (1, 4, 5, 5))
    assert odd_report.macs_paper == 11 * 11 * 4 * 4 * 9


def test_multihead_attention_matches_flop_counter():
    attention = nn.MultiheadAttention(16, 4, batch_first=True, kdim=8, vdim=12)  # training mode: no fast path
    query, key, value = torch.randn(2, 5, 16), torch.randn(2, 7, 8), torch.randn(2, 7, 12)
    report = count_macs(attention, query.shape, key.shape, value.shape)
    assert report.macs == flop_counter_macs(attention, query, key, value)


class _SparseLike(nn.Module):
    """Stands in for a sparse conv: data-dependent cost reported as ``last_macs`` after forward."""

    def __init__(self) -> None:
        super().__init__()
        self.inner = nn.Linear(3, 3)  # not to be counted: the module reports its own cost
        self.last_macs = 0

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        active = int((points > 0).sum())
        self.last_macs = active * 100
        return points


class _CustomMatmul(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(4, 6))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return features @ self.weight

    def analytic_macs(self, inputs: tuple, output: torch.Tensor) -> int:
        return inputs[0].numel() * self.weight.shape[1]


def test_dynamic_macs_are_summed_per_call():
    sparse = _SparseLike()
    model = nn.Sequential(sparse, sparse, nn.Linear(4, 2))  # the sparse module runs twice
    points = torch.tensor([[1.0, -1.0, 2.0, 0.0], [3.0, 1.0, -2.0, 5.0]])  # 5 positive
    with MacRecorder(model) as recorder:
        model(points)
    report = recorder.report()
    assert report.dynamic_macs == 2 * 500
    assert report.macs == 2 * 500 + 2 * 4 * 2
    assert report.input_shapes == ((2, 4),)
    assert dynamic_macs(model) == 500  # the last call only
    with MacRecorder(model) as recorder:  # hooks were removed: a new recorder starts from zero
        model(points[:1])
    assert recorder.report().dynamic_macs == 2 * 200


def test_custom_analytic_macs_and_params():
    model = nn.Sequential(_CustomMatmul(), nn.Linear(6, 3, bias=False))
    report = count_macs(model, (5, 4))
    assert report.macs == 5 * 4 * 6 + 5 * 6 * 3
    assert count_params(model) == 24 + 18
    model[1].weight.requires_grad_(False)
    assert count_params(model, trainable_only=True) == 24


def test_counter_caches_per_shape_and_leaves_model_untouched():
    model = create_model("centre_detector_tiny", preset="small")  # training mode
    bn = next(m for m in model.modules() if isinstance(m, nn.BatchNorm2d))
    running_mean = bn.running_mean.clone()
    counter = ComputeCounter(model)
    first = counter.report((1, 32, 128, 128))
    assert counter.report((1, 32, 128, 128)) is first
    double = counter.report((2, 32, 128, 128))
    assert double.macs == 2 * first.macs
    assert model.training and bn.num_batches_tracked.item() == 0
    assert torch.equal(bn.running_mean, running_mean)
    assert next(model.parameters()).device.type == "cpu"


def test_report_sum_and_errors():
    a = ComputeReport(params=10, macs=100, macs_paper=120, by_stage={"x": 100}, input_shapes=((1, 2),))
    b = ComputeReport(params=5, macs=50, macs_paper=50, dynamic_macs=50, by_stage={"x": 20, "y": 30})
    total = a + b
    assert (total.params, total.macs, total.macs_paper, total.dynamic_macs) == (15, 150, 170, 50)
    assert total.by_stage == {"x": 120, "y": 30}
    assert math.isclose(total.gmacs, 1.5e-7)
    with pytest.raises(ValueError, match="input shapes"):
        count_macs(nn.Linear(2, 2), (0, 2))
    with pytest.raises(ValueError, match="at least one"):
        count_macs(nn.Linear(2, 2))
