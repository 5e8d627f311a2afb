"""Network slimming: exact surgery on zeroed channels, narrower rebuilt models, checkpoints, sparsity training."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable

import numpy as np
import pytest
import torch
from torch import nn

from models.channel_surgery import NORM_TYPES, apply_channel_table
from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.compute import count_params
from models.registry import create_model
from models.segmenter.spvcnn import PointTensor
from models.slimming.channels import trace_channels
from models.slimming.penalty import slimming_penalty
from models.slimming.prune import prune_checkpoint, prune_model, select_channels
from models.sparse import SparseTensor
from models.sparse import last_forward_macs as sparse_macs
from radar.profiles import get_profile


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _cloud(seed: int = 0, n: int = 500, extent: int = 20) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    flat = torch.randperm(extent**3, generator=g)[:n]
    xyz = torch.stack([flat // extent**2, (flat // extent) % extent, flat % extent], dim=1)
    coords = torch.cat([torch.zeros(n, 1, dtype=torch.int64), xyz], dim=1)
    return coords, torch.randn(n, 4, generator=g)


def _sparse_input():
    coords, feats = _cloud()
    return lambda: SparseTensor(coords, feats)


def _point_input():
    coords, feats = _cloud()
    return lambda: PointTensor(coords[:, 0].contiguous(), coords[:, 1:].float() + 0.5, feats)


def _views():
    r, a, d = get_profile("small").shape
    g = torch.Generator().manual_seed(0)
    views = [torch.randn(2, 1, r, d, generator=g), torch.randn(2, 1, r, a, generator=g),
             torch.randn(2, 1, a, d, generator=g)]
    return lambda: views


def _detector_input():
    r, a, d = get_profile("small").shape
    x = torch.randn(2, d, r, a, generator=torch.Generator().manual_seed(0))
    return lambda: (x,)


def _flat(output) -> torch.Tensor:
    if isinstance(output, dict):
        return torch.cat([v.flatten() for _, v in sorted(output.items())])
    return output.flatten()


# name -> (inputs factory, returns a tuple/list of forward arguments or one argument)
CASES: dict[str, Callable[[], Callable]] = {
    "centre_detector_tiny": _detector_input,
    "minkunet_tiny": _sparse_input,
    "spvcnn_tiny": _point_input,
    "smvanet_tiny": _views,
}


def _run(model: nn.Module, inputs: Callable) -> torch.Tensor:
    args = inputs()
    return _flat(model(*args) if isinstance(args, tuple | list) else model(args))


def _randomise_norms(model: nn.Module, seed: int = 0) -> None:
    """Non-trivial BatchNorm statistics, so zeroed channels are the only exact zeros."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in model.modules():
            if isinstance(m, NORM_TYPES):
                n = m.num_features
                m.weight.copy_(torch.rand(n, generator=g) + 0.5)
                m.bias.copy_(torch.rand(n, generator=g) * 0.2 - 0.1)
                m.running_mean.copy_(torch.rand(n, generator=g) * 0.2 - 0.1)
                m.running_var.copy_(torch.rand(n, generator=g) + 0.5)


def _zero_third_of_each_group(model: nn.Module) -> int:
    """Zero scale and shift of the first third of every prunable group (in all its BatchNorms)."""
    zeroed = 0
    with torch.no_grad():
        for group in trace_channels(model):
            if not group.prunable or group.size < 3:
                continue
            n = group.size // 3
            zeroed += n
            for part in group.norms:
                part.norm.weight[part.offset:part.offset + n] = 0
                part.norm.bias[part.offset:part.offset + n] = 0
    return zeroed


@pytest.mark.parametrize("name", sorted(CASES))
def test_removing_zeroed_channels_leaves_outputs_unchanged(name):
    inputs = CASES[name]()
    model = create_model(name).eval()
    _randomise_norms(model)
    zeroed = _zero_third_of_each_group(model)
    assert zeroed > 0
    with torch.no_grad():
        before = _run(model, inputs)
    groups = trace_channels(model)
    # the zeroed channels are exactly those of importance 0; a ratio of that size removes them
    candidates = sum(g.size for g in groups if g.prunable)
    selection = select_channels(groups, zeroed / candidates)
    assert selection.removed == zeroed
    assert all(bool((g.importance()[selection.keep[i]] > 0).all()) for i, g in enumerate(groups) if g.prunable)
    pruned = copy.deepcopy(model)
    prune_model(pruned, trace_channels(pruned), selection.keep)
    with torch.no_grad():
        after = _run(pruned.eval(), inputs)
    torch.testing.assert_close(after, before, rtol=1e-4, atol=1e-4)
    assert count_params(pruned) < count_params(model)
    # a control: removing channels that were not zeroed does change the outputs
    control = copy.deepcopy(model)
    groups = trace_channels(control)
    keep = {i: torch.arange(g.size - g.size // 3 if g.prunable and g.size >= 3 else g.size)
            for i, g in enumerate(groups)}  # drops the last third instead of the zeroed first third
    prune_model(control, groups, keep)
    with torch.no_grad():
        assert not torch.allclose(_run(control.eval(), inputs), before, atol=1e-3)


def _checkpoint(name: str, model: nn.Module) -> Checkpoint:
    profile = get_profile("small")
    return Checkpoint(model_name=name, config={"preset": "small"}, state_dict=model.state_dict(), preset="small",
                      class_names=tuple(profile.all_class_names))


@pytest.mark.parametrize("name", sorted(CASES))
def test_pruned_checkpoint_is_narrower_trains_and_reloads_alone(name, tmp_path):
    inputs = CASES[name]()
    model = create_model(name, preset="small")
    _randomise_norms(model, seed=1)
    pruned_ckpt, report = prune_checkpoint(_checkpoint(name, model), ratio=0.4)
    assert report.params_after < report.params_before
    assert 0 < report.removed_channels <= round(0.4 * report.candidate_channels)
    for before, after in report.widths.values():
        assert 1 <= after <= before  # never emptied
    assert any(after < before for before, after in report.widths.values())
    assert pruned_ckpt.config["channels"]  # the narrower architecture travels in the config
    path = save_checkpoint(pruned_ckpt, tmp_path / "pruned.pt")
    loaded = load_checkpoint(path)
    rebuilt = loaded.build()  # from the checkpoint alone
    assert count_params(rebuilt) == report.params_after
    # channel counts in the rebuilt model are those of the report
    groups = trace_channels(rebuilt)
    widths = {g.name: g.size for g in groups if g.prunable}
    assert widths == {k: after for k, (_, after) in report.widths.items()}
    # fewer MACs: dense models by the analytic counter, sparse ones by their recorded pair counts
    if report.macs_before is not None:
        assert report.macs_after < report.macs_before
    else:
        original = _checkpoint(name, model).build()
        with torch.no_grad():
            _run(original, inputs)
            _run(rebuilt, inputs)
        assert sparse_macs(rebuilt) < sparse_macs(original)
    # forward + backward
    rebuilt.train()
    loss = _run(rebuilt, inputs).square().mean()
    loss.backward()
    assert sum(p.grad.abs().sum() for p in rebuilt.parameters() if p.grad is not None) > 0
    # pruning the pruned checkpoint again keeps one table relative to the default build
    again, report2 = prune_checkpoint(loaded, ratio=0.3)
    assert report2.params_after < report.params_after
    assert count_params(again.build()) == report2.params_after


def test_budget_in_params_is_met():
    model = create_model("centre_detector_tiny")
    _randomise_norms(model, seed=2)
    budget = int(0.7 * count_params(model))
    pruned, report = prune_checkpoint(_checkpoint("centre_detector_tiny", model), params=budget)
    assert report.params_after <= budget
    assert report.params_after > 0.5 * count_params(model)  # not far below: the ratio was searched
    with pytest.raises(ValueError, match="params budget"):
        prune_checkpoint(_checkpoint("minkunet_tiny", create_model("minkunet_tiny")), macs=1000)


def test_channel_table_errors_name_the_layer():
    model = create_model("minkunet_tiny")
    with pytest.raises(ValueError, match="no layer 'nowhere'"):
        apply_channel_table(model, {"nowhere": [1, 1]})
    with pytest.raises(ValueError, match="stem.0.1"):
        apply_channel_table(model, {"stem.0.1": [10_000]})
    with pytest.raises(ValueError, match="ratio"):
        select_channels(trace_channels(model), 1.0)


def test_sparsity_training_drives_scales_toward_zero():
    """A few steps of a task loss plus lambda * sum |gamma| shrink the BatchNorm scales; without the
    penalty they stay near 1."""
    inputs = _sparse_input()
    target = torch.randint(0, get_profile("small").num_classes, (500,), generator=torch.Generator().manual_seed(0))

    def train(slim_lambda: float) -> float:
        torch.manual_seed(0)
        model = create_model("minkunet_tiny")
        optimiser = torch.optim.SGD(model.parameters(), lr=0.05)
        for _ in range(30):
            loss = nn.functional.cross_entropy(model(inputs()), target)
            if slim_lambda:
                loss = loss + slim_lambda * slimming_penalty(model)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
        return float(torch.cat([m.weight.detach().abs() for m in model.modules()
                                if isinstance(m, NORM_TYPES)]).mean())

    plain, sparse = train(0.0), train(0.3)  # strong lambda: 30 steps must show it
    assert plain > 0.9
    assert sparse < 0.8 * plain


def test_pruned_checkpoints_serve_through_erasenet_with_fewer_macs(tmp_path):
    """The service's path: EraseNet.from_checkpoints on pruned checkpoints, compute report included."""
    from models.erasenet.model import EraseNet
    from radar.centres import Centres
    from radar.simulate import simulate_sequence

    frame = next(iter(simulate_sequence("small", 1, seed=3)))
    cube = frame.cube
    seeds = Centres.from_bins(np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin]
                                        for o in frame.objects if o.n_voxels]))
    paths = {}
    for stage, name in (("det", "centre_detector_tiny"), ("seg", "minkunet_tiny")):
        torch.manual_seed(0)
        model = create_model(name, preset="small")
        _randomise_norms(model, seed=3)
        checkpoint = dataclasses.replace(_checkpoint(name, model), normalisation={"mean": 60.0, "std": 8.0})
        paths[stage] = save_checkpoint(checkpoint, tmp_path / f"{stage}.pt")
        paths[f"{stage}_pruned"] = save_checkpoint(prune_checkpoint(checkpoint, ratio=0.5)[0],
                                                   tmp_path / f"{stage}_pruned.pt")
    full = EraseNet.from_checkpoints(paths["det"], paths["seg"], score_threshold=0.0, max_objects=2)
    slim = EraseNet.from_checkpoints(paths["det_pruned"], paths["seg_pruned"], score_threshold=0.0, max_objects=2)
    assert 0 < slim.segment(cube).compute.detect_macs < full.segment(cube).compute.detect_macs
    # the same seeds (the same ROI) for both segmenters: fewer channels, fewer MACs
    full_macs = full.segment(cube, centres=seeds).compute.segment_macs
    slim_macs = slim.segment(cube, centres=seeds).compute.segment_macs
    assert 0 < slim_macs < full_macs
    assert slim.params["detector"] < full.params["detector"] and slim.params["segmenter"] < full.params["segmenter"]
