"""Stage-1 centre detector: shapes per preset, targets, loss, decoding, overfitting, registry."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.detector import (
    VARIANTS,
    BiFPNNeck,
    CentreDetector,
    CentreNetHead,
    build_centre_targets,
    build_efficientnet,
    focal_loss,
    render_heatmap,
)
from models.registry import UnknownModelError, create_model, list_models, register_model
from radar.profiles import get_profile
from radar.simulate.simulator import simulate_sequence


@pytest.mark.parametrize("preset", ["small", "carrada", "nxp"])
def test_output_shapes_and_finite_on_every_preset(preset):
    n_range, n_angle, n_doppler = get_profile(preset).shape
    torch.manual_seed(0)
    model = create_model("centre_detector_tiny", preset=preset).eval()
    with torch.no_grad():
        outputs = model(torch.randn(2, n_doppler, n_range, n_angle))
    grid = (n_range // 4, n_angle // 4)
    assert set(outputs) == {"heatmap", "heatmap_logits", "offset", "doppler"}
    assert outputs["heatmap"].shape == (2, 1, *grid)
    assert outputs["offset"].shape == (2, 2, *grid)
    assert outputs["doppler"].shape == (2, 1, *grid)
    for value in outputs.values():
        assert torch.isfinite(value).all()
    assert ((outputs["heatmap"] > 0) & (outputs["heatmap"] < 1)).all()


def test_full_size_detector_runs_and_matches_chosen_variant():
    model = create_model("centre_detector", preset="small").eval()
    params = sum(p.numel() for p in model.parameters())
    assert 1.9e6 < params < 2.2e6  # the chosen "smaller" variant, about the paper's 2.08 M
    with torch.no_grad():
        outputs = model(torch.randn(1, 32, 128, 128))
    assert outputs["heatmap"].shape == (1, 1, 32, 32)
    # initial heatmap is the prior 0.1 almost everywhere (bias -2.19)
    assert abs(outputs["heatmap"].mean().item() - 0.1) < 0.05


def test_odd_grid_is_padded_inside_and_cropped_back():
    n_range, n_angle, n_doppler = 50, 70, 8
    x = np.linspace(-10, 10, n_range * n_angle, dtype=np.float32).reshape(n_range, n_angle)
    y = np.abs(x) + 1
    backbone = build_efficientnet(in_channels=5, width_mult=0.25, depth_mult=0.25)
    neck = BiFPNNeck(backbone.feature_channels, channels=8, num_layers=1)
    head = CentreNetHead(doppler_bins=n_doppler, in_channels=8, head_channels=8)
    model = CentreDetector(doppler_bins=n_doppler, cartesian=(x, y), backbone=backbone, neck=neck, head=head)
    with torch.no_grad():
        outputs = model.eval()(torch.randn(1, n_doppler, n_range, n_angle))
    assert outputs["heatmap"].shape == (1, 1, 13, 18)  # ceil(50/4), ceil(70/4)
    with pytest.raises(ValueError, match="expected log power"):
        model(torch.randn(1, n_doppler, n_range + 1, n_angle))


def test_cartesian_channels_are_the_profile_grid_normalised():
    profile = get_profile("small")
    model = create_model("centre_detector_tiny", preset="small")
    x, y = profile.ra_cartesian
    scale = np.hypot(x, y).max()
    np.testing.assert_allclose(model.cartesian[0, 0].numpy(), x / scale, atol=1e-6)
    np.testing.assert_allclose(model.cartesian[0, 1].numpy(), y / scale, atol=1e-6)
    assert model.cartesian[0, 0].min() < -0.5 and model.cartesian[0, 1].max() == pytest.approx(1.0)


def test_render_heatmap_gaussian_values():
    # centre at range bin 41.5, angle bin 30.2 -> cell (10, 7) at stride 4
    heatmap = render_heatmap([[41.5, 30.2, 3.0]], (64, 64))
    assert heatmap.shape == (16, 16)
    assert heatmap[10, 7] == 1.0
    assert heatmap[9, 7] == pytest.approx(math.exp(-1 / (2 * (1 / 3) ** 2)))  # range neighbour
    assert heatmap[10, 8] == pytest.approx(math.exp(-1 / (2 * (1 / 2) ** 2)))  # angle neighbour
    assert heatmap[11, 6] == pytest.approx(math.exp(-4.5 - 2.0))
    assert heatmap[10, 9] == 0 and heatmap[12, 7] == 0  # radius 1 cell
    assert np.count_nonzero(heatmap) == 9


def test_targets_layout_and_errors():
    targets = build_centre_targets([[[41.5, 30.2, 3.5]], []], (64, 64), max_objects=4)
    assert targets["heatmap"].shape == (2, 1, 16, 16)
    assert targets["indices"][0, 0].item() == 10 * 16 + 7
    np.testing.assert_allclose(targets["offsets"][0, 0].numpy(), [41.5 / 4 - 10, 30.2 / 4 - 7], atol=1e-6)
    assert targets["doppler"][0, 0].item() == pytest.approx(3.5)
    assert targets["mask"].tolist() == [[True, False, False, False], [False] * 4]
    assert targets["heatmap"][1].sum() == 0
    with pytest.raises(ValueError, match="outside"):
        build_centre_targets([[[64.0, 3.0, 1.0]]], (64, 64))
    with pytest.raises(ValueError, match="max_objects"):
        build_centre_targets([[[1.0, 1.0, 1.0]] * 3], (64, 64), max_objects=2)


def test_focal_loss_hand_computed():
    # p = sigmoid(0) = 0.5 everywhere; targets: one positive, one penalty-reduced negative (y = 0.5),
    # one plain negative.
    logits = torch.zeros(1, 1, 1, 3)
    target = torch.tensor([[[[1.0, 0.5, 0.0]]]])
    log_half = math.log(0.5)
    positive = (1 - 0.5) ** 2 * log_half
    reduced_negative = (1 - 0.5) ** 4 * 0.5**2 * log_half
    negative = 0.5**2 * log_half
    expected = -(positive + reduced_negative + negative) / 1
    assert focal_loss(logits, target).item() == pytest.approx(expected, rel=1e-6)
    # the head uses the same alpha 2, beta 4
    head = CentreNetHead(doppler_bins=4, in_channels=4, head_channels=4)
    no_objects = {
        "heatmap": target,
        "indices": torch.zeros(1, 1, dtype=torch.long),
        "offsets": torch.zeros(1, 1, 2),
        "doppler": torch.zeros(1, 1),
        "mask": torch.zeros(1, 1, dtype=torch.bool),
    }
    outputs = {"heatmap_logits": logits, "offset": torch.zeros(1, 2, 1, 3), "doppler": torch.zeros(1, 1, 1, 3)}
    losses = head.compute_loss(outputs, no_objects)
    assert losses["heatmap"].item() == pytest.approx(expected, rel=1e-6)
    assert losses["offset"].item() == 0 and losses["doppler"].item() == 0
    # two positives halve the normalised sum; no positive divides by 1
    two_pos = torch.tensor([[[[1.0, 1.0, 0.0]]]])
    assert focal_loss(logits, two_pos).item() == pytest.approx(-(2 * positive + negative) / 2, rel=1e-6)
    assert focal_loss(logits, torch.zeros_like(target)).item() == pytest.approx(-3 * negative, rel=1e-6)


def test_offset_and_doppler_l1_at_centres():
    head = CentreNetHead(doppler_bins=16, in_channels=8, head_channels=8)
    targets = build_centre_targets([[[9.0, 21.0, 5.0], [30.0, 2.0, 12.0]]], (32, 32))
    # cells (2, 5) offset (0.25, 0.25) and (7, 0) offset (0.5, 0.5)
    outputs = {
        "heatmap_logits": torch.zeros(1, 1, 8, 8),
        "offset": torch.zeros(1, 2, 8, 8),
        "doppler": torch.full((1, 1, 8, 8), 100.0),
    }
    outputs["doppler"][0, 0, 2, 5] = 6.0  # error 1
    outputs["doppler"][0, 0, 7, 0] = 9.0  # error 3
    outputs["offset"][0, :, 7, 0] = torch.tensor([0.5, 1.5])  # errors 0 and 1
    losses = head.compute_loss(outputs, targets)
    assert losses["doppler"].item() == pytest.approx(2.0, rel=1e-4)
    assert losses["offset"].item() == pytest.approx((0.25 + 0.25 + 0.0 + 1.0) / 4, rel=1e-4)
    assert losses["total"].item() == pytest.approx(
        losses["heatmap"].item() + losses["offset"].item() + losses["doppler"].item(), rel=1e-6
    )


def test_decode_recovers_planted_centres():
    head = CentreNetHead(doppler_bins=32)
    centres = [
        np.array([[10.3, 50.9, 7.25], [70.0, 12.6, 20.5], [100.8, 101.1, 3.0]]),
        np.array([[3.2, 120.7, 30.0]]),
    ]
    targets = build_centre_targets(centres, (128, 128))
    heatmap = targets["heatmap"].clone()
    heatmap[0, 0, 10, 28] = 0.05  # an isolated weak peak, below the threshold
    offset = torch.zeros(2, 2, 32, 32)
    doppler = torch.zeros(2, 1, 32, 32)
    for b in range(2):
        for slot in range(int(targets["mask"][b].sum())):
            row, col = divmod(int(targets["indices"][b, slot]), 32)
            offset[b, :, row, col] = targets["offsets"][b, slot]
            doppler[b, 0, row, col] = targets["doppler"][b, slot]
    detections = head.decode({"heatmap": heatmap, "offset": offset, "doppler": doppler}, k=10, score_threshold=0.1)
    assert len(detections) == 2
    for frame, expected in zip(detections, centres, strict=True):
        assert len(frame["score"]) == len(expected)
        assert (frame["score"] == 1).all()
        found = torch.stack([frame["range_bin"], frame["angle_bin"], frame["doppler_bin"]], 1).numpy()
        order = np.lexsort(found.T[::-1])
        np.testing.assert_allclose(found[order], expected[np.lexsort(expected.T[::-1])], atol=1e-4)
    lowered = head.decode({"heatmap": heatmap, "offset": offset, "doppler": doppler}, k=10, score_threshold=0.01)
    assert len(lowered[0]["score"]) == 4 and lowered[0]["score"][-1].item() == pytest.approx(0.05)
    top1 = head.decode({"heatmap": heatmap, "offset": offset, "doppler": doppler}, k=1, score_threshold=0.1)
    assert [len(f["score"]) for f in top1] == [1, 1]


def _simulated_batch(n_frames: int = 2):
    frames = list(simulate_sequence("small", n_frames, seed=3))
    inputs, centres = [], []
    for frame in frames:
        log_power = frame.log_power()
        log_power = (log_power - log_power.mean()) / log_power.std()
        inputs.append(np.transpose(log_power, (2, 0, 1)))  # (D, R, A)
        centres.append(
            np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels > 0])
        )
    return torch.from_numpy(np.stack(inputs)).float(), centres


def test_overfits_a_fixed_simulated_batch():
    inputs, centres = _simulated_batch()
    assert all(len(c) > 0 for c in centres)
    targets = build_centre_targets(centres, (128, 128))
    torch.manual_seed(0)
    model = create_model("centre_detector_tiny", preset="small")
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-2)
    history = []
    for _ in range(40):
        losses = model.compute_loss(model(inputs), targets)
        assert all(torch.isfinite(v) for v in losses.values())
        optimiser.zero_grad()
        losses["total"].backward()
        optimiser.step()
        history.append({k: v.item() for k, v in losses.items()})
    assert history[-1]["total"] < 0.2 * history[0]["total"]
    assert history[-1]["heatmap"] < 0.2 * history[0]["heatmap"]
    # batch statistics: 40 steps are too few for BN running stats at momentum 0.01
    with torch.no_grad():
        detections = model.decode(model(inputs), k=20, score_threshold=0.5)
    for frame, expected in zip(detections, centres, strict=True):
        assert len(frame["score"]) == len(expected)
        found = torch.stack([frame["range_bin"], frame["angle_bin"]], 1).numpy()
        distance = np.abs(found[:, None, :] - expected[None, :, :2]).max(axis=2)  # (found, true) bins
        assert (distance.min(axis=0) < 2.0).all()


# ------------------------------------------------------------------------------------ registry
def test_registry_lists_and_builds_detectors():
    assert {"centre_detector", "centre_detector_tiny"} <= set(list_models())
    model = create_model("centre_detector", preset="small", variant="literal_sep", width_mult=0.5)
    assert isinstance(model, CentreDetector)
    assert set(VARIANTS) == {"b0", "slim", "slim_sep", "literal", "literal_sep"}


def test_registry_errors():
    with pytest.raises(UnknownModelError, match="centre_detector"):
        create_model("no_such_model")
    with pytest.raises(ValueError, match="variant"):
        create_model("centre_detector", variant="huge")
    with pytest.raises(ValueError, match="width_mult"):
        create_model("centre_detector", preset="small", width_mult=0)
    with pytest.raises(ValueError, match="neck_channels"):
        create_model("centre_detector", preset="small", neck_channels=0)
    with pytest.raises(TypeError):
        create_model("centre_detector", preset="small", colour="red")
    with pytest.raises(KeyError, match="unknown radar preset"):
        create_model("centre_detector_tiny", preset="nowhere")
    with pytest.raises(ValueError, match="already registered"):
        register_model("centre_detector")(lambda **cfg: torch.nn.Identity())
    with pytest.raises(ValueError, match="non-empty"):
        register_model("")


def test_frozen_detector_equals_the_eager_one_and_folds_every_batch_norm():
    from models.detector.inference import FrozenDetector

    torch.manual_seed(0)
    detector = create_model("centre_detector_tiny", preset="small").eval()
    batch_norms = sum(isinstance(m, torch.nn.BatchNorm2d) for m in detector.modules())
    log_power = torch.randn(1, 32, 128, 128)
    frozen = FrozenDetector(detector, tuple(log_power.shape))
    assert frozen.folded_batch_norms == batch_norms > 0
    with torch.no_grad():
        expected, got = detector(log_power), frozen(log_power)
    for name in expected:
        torch.testing.assert_close(got[name], expected[name], rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="traced for input"):
        frozen(torch.randn(1, 32, 64, 128))


def test_centre_weights_scale_only_the_positives_of_the_focal_loss():
    """``--class-weights``: a weight per object at its centre cell (1 elsewhere) multiplies the positive term."""
    from models.detector.centernet import focal_loss
    from models.detector.targets import build_centre_targets

    centres = [np.array([[10.0, 20.0, 3.0], [40.0, 8.0, 5.0]])]
    plain = build_centre_targets(centres, (64, 64))
    weighted = build_centre_targets(centres, (64, 64), centre_weights=[np.array([3.0, 1.0])])
    weight = weighted["peak_weight"]
    assert weight.shape == plain["heatmap"].shape and "peak_weight" not in plain
    assert sorted(weight.unique().tolist()) == [1.0, 3.0] and int((weight == 3.0).sum()) == 1
    assert weight.flatten()[plain["indices"][0, 0]] == 3.0  # at the first object's centre cell
    logits = torch.zeros_like(plain["heatmap"])  # p = 0.5 everywhere
    base = focal_loss(logits, plain["heatmap"])
    heavier = focal_loss(logits, plain["heatmap"], peak_weight=weight)
    positive_term = 0.5 ** 2 * np.log(2.0) / 2  # one positive's share: (1 - p)^2 * -log p / n_pos
    assert float(heavier - base) == pytest.approx(2 * positive_term, rel=1e-5)


def test_per_class_targets_draw_each_object_in_its_class_channel_only():
    centres = [np.array([[10.0, 20.0, 3.0], [40.0, 8.0, 5.0], [60.0, 60.0, 1.0]])]
    plain = build_centre_targets(centres, (128, 128))
    per_class = build_centre_targets(centres, (128, 128), heatmap_classes=3, classes=[np.array([0, 2, 2])])
    heat = per_class["heatmap"][0]
    assert heat.shape == (3, 32, 32)
    flat = heat.reshape(3, -1)
    cells = plain["indices"][0, :3]
    assert flat[0, cells[0]] == 1 and flat[2, cells[1]] == 1 and flat[2, cells[2]] == 1
    assert flat[1].max() == 0 and flat[0, cells[1]] == 0 and flat[2, cells[0]] == 0
    torch.testing.assert_close(heat.amax(0), plain["heatmap"][0, 0])  # together: the class-agnostic map
    for key in ("indices", "offsets", "doppler", "mask"):
        torch.testing.assert_close(per_class[key], plain[key])
    with pytest.raises(ValueError, match="class per object"):
        build_centre_targets(centres, (128, 128), heatmap_classes=3)
    with pytest.raises(ValueError, match=r"in \[0, 3\)"):
        build_centre_targets(centres, (128, 128), heatmap_classes=3, classes=[np.array([0, 3, 1])])


def test_per_class_head_merges_gained_class_maps_into_one_heatmap():
    """``heatmap_classes``: decoding reads ``max_c min(1, gain_c p_c)``; the gains travel in the state dict."""
    torch.manual_seed(0)
    detector = create_model("centre_detector", preset="small", width_mult=0.25, depth_mult=0.25, neck_channels=16,
                            neck_layers=1, head_channels=16, heatmap_classes=3).eval()
    assert "head.class_gain" in detector.state_dict()
    log_power = torch.randn(2, 32, 128, 128)
    with torch.no_grad():
        out = detector(log_power)
        assert out["class_heatmap"].shape == (2, 3, 32, 32) and out["heatmap"].shape == (2, 1, 32, 32)
        torch.testing.assert_close(out["heatmap"], out["class_heatmap"].amax(1, keepdim=True))
        detector.head.class_gain.copy_(torch.tensor([4.0, 1.0, 0.5]))
        gained = detector(log_power)
    expected = torch.stack([(out["class_heatmap"][:, 0] * 4).clamp(max=1), out["class_heatmap"][:, 1],
                            out["class_heatmap"][:, 2] * 0.5], 1).amax(1, keepdim=True)
    torch.testing.assert_close(gained["heatmap"], expected)
    assert gained["heatmap"].max() <= 1.0
    targets = build_centre_targets([np.array([[10.0, 20.0, 3.0]]), np.zeros((0, 3))], (128, 128),
                                   heatmap_classes=3, classes=[np.array([1]), np.zeros(0)])
    losses = detector.compute_loss(gained, targets)
    assert torch.isfinite(losses["total"]) and losses["heatmap"] > 0
    with pytest.raises(ValueError, match="does not match"):
        detector.compute_loss(gained, build_centre_targets([np.array([[10.0, 20.0, 3.0]])] * 2, (128, 128)))


def test_doppler_compression_width_is_an_option():
    wide = create_model("centre_detector", preset="small", width_mult=0.25, depth_mult=0.25, neck_channels=16,
                        neck_layers=1, head_channels=16, doppler_channels=12).eval()
    assert wide.doppler_compress.out_channels == 12
    assert wide.backbone.stem[0].in_channels == 14  # 12 Doppler + 2 Cartesian channels
    with torch.no_grad():
        assert wide(torch.randn(1, 32, 128, 128))["heatmap"].shape == (1, 1, 32, 32)
    with pytest.raises(ValueError, match="doppler_channels"):
        create_model("centre_detector", preset="small", doppler_channels=0)
