"""The 2-D baselines: exact parameter counts, shapes, MAC counters, and the MVRSS losses."""

import math

import pytest
import torch
import torch.nn.functional as F
from torch.utils.flop_counter import FlopCounterMode

from models.baselines import MultiViewLoss, class_weights_from_counts, coherence_loss, soft_dice_loss
from models.compute import count_macs, count_params
from models.registry import create_model
from radar.profiles import get_profile


@pytest.mark.parametrize(("name", "config", "expected"), [
    ("tmvanet", {}, 5_630_984),  # MVRSS's TMVA-Net, 4 classes
    ("smvanet", {}, 4_739_336),  # its single-frame variant
    ("unet", {"view": "ra"}, 31_036_676),  # classic U-Net, 1 input channel, 4 classes: the paper's 31.04 M
    ("unet", {"view": "rd"}, 31_036_676),
])
def test_parameter_counts_equal_the_reference(name, config, expected):
    assert count_params(create_model(name, preset="carrada", **config)) == expected


def _views(batch, frames, preset):
    r, a, d = get_profile(preset).shape if isinstance(preset, str) else preset
    return [torch.randn(batch, frames, r, d), torch.randn(batch, frames, r, a), torch.randn(batch, frames, a, d)]


@pytest.mark.parametrize("name", ["tmvanet_tiny", "smvanet_tiny"])
@pytest.mark.parametrize("grid", [(16, 16, 8), (16, 12, 8)])  # square (as CARRADA) and R != A (as nxp)
def test_multi_view_output_shapes(name, grid):
    model = create_model(name).eval()
    rd, ra, ad = _views(2, model.n_frames, grid)
    with torch.no_grad():
        out = model(rd, ra, ad)
    r, a, d = grid
    assert set(out) == {"rd", "ra"}
    assert out["rd"].shape == (2, 4, r, d) and out["ra"].shape == (2, 4, r, a)


def test_multi_view_rejects_bad_inputs():
    model = create_model("tmvanet_tiny")
    rd, ra, ad = _views(1, 5, (16, 16, 8))
    with pytest.raises(ValueError, match="multiples of 4"):
        model(*_views(1, 5, (18, 16, 8)))
    with pytest.raises(ValueError, match=r"\(B, 5, H, W\)"):
        model(rd[:, :3], ra, ad)
    with pytest.raises(ValueError, match="must share R, A, D"):
        model(rd, ra[..., :12], ad)
    with pytest.raises(ValueError, match="n_frames must be 5"):
        create_model("tmvanet_tiny").__class__(num_classes=4, temporal=True, n_frames=3)


def test_unet_shapes_odd_sizes_and_view():
    model = create_model("unet_tiny", view="rd").eval()
    with torch.no_grad():
        out = model(torch.randn(1, 1, 20, 18))
    assert set(out) == {"rd"} and out["rd"].shape == (1, 4, 20, 18)
    with pytest.raises(ValueError, match="view must be"):
        create_model("unet_tiny", view="ad")


@pytest.mark.parametrize(("name", "shapes"), [
    ("tmvanet_tiny", [(2, 5, 16, 8), (2, 5, 16, 12), (2, 5, 12, 8)]),
    ("smvanet_tiny", [(1, 1, 16, 8), (1, 1, 16, 16), (1, 1, 16, 8)]),
    ("unet_tiny", [(1, 1, 20, 18)]),
])
def test_mac_counters_against_flop_counter(name, shapes):
    model = create_model(name).eval()
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        model(*[torch.randn(s) for s in shapes])
    report = count_macs(model, *shapes)
    assert report.macs == counter.get_total_flops() // 2
    # the paper's counter overcounts each transposed conv: by k_h * k_w = 2 for RD, 4 for RA and U-Net
    assert report.macs_paper > report.macs


def test_full_size_macs_at_carrada_match_the_reference_measurement():
    """docs/design.md section 9: TMVA-Net 95.62 G, SMVA-Net 65.72 G (correct counter) at 256x256 / 256x64."""
    tmva = count_macs(create_model("tmvanet", preset="carrada"), (1, 5, 256, 64), (1, 5, 256, 256), (1, 5, 256, 64))
    smva = count_macs(create_model("smvanet", preset="carrada"), (1, 1, 256, 64), (1, 1, 256, 256), (1, 1, 256, 64))
    assert round(tmva.macs / 1e9, 2) == 95.62
    assert round(smva.macs / 1e9, 2) == 65.72
    # the decoders are the same: the transposed-conv overcount is too
    assert tmva.macs_paper - tmva.macs == smva.macs_paper - smva.macs


# --------------------------------------------------------------------------- losses
def test_class_weights_are_normalised_inverse_frequencies():
    weights = class_weights_from_counts([900, 50, 0, 50])
    assert weights.tolist() == pytest.approx([1 / 900 / (1 / 900 + 3 / 50), 1 / 50 / (1 / 900 + 3 / 50),
                                              1 / 50 / (1 / 900 + 3 / 50), 1 / 50 / (1 / 900 + 3 / 50)])
    assert float(weights.sum()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="not all zero"):
        class_weights_from_counts([0, 0])


def test_soft_dice_by_hand():
    # two pixels, two classes; logits chosen so that softmax gives p = (0.5, 0.5) for both pixels
    logits = torch.zeros(1, 2, 1, 2)
    target = torch.tensor([[[0, 1]]])
    # intersection = 0.5 + 0.5 = 1; cardinality = sum p^2 (4 * 0.25 = 1) + sum t^2 (2) = 3
    assert float(soft_dice_loss(logits, target, eps=0.0)) == pytest.approx(1 - 2 / 3)
    perfect = torch.tensor([[[[50.0, -50.0]], [[-50.0, 50.0]]]])
    assert float(soft_dice_loss(perfect, target)) == pytest.approx(0.0, abs=1e-6)


def test_coherence_zero_for_coherent_masks_and_positive_otherwise():
    # RA and RD predictions that are one-hot images of the same RAD objects: per range bin the same classes
    ra_mask = torch.zeros(1, 8, 6, dtype=torch.long)
    rd_mask = torch.zeros(1, 8, 4, dtype=torch.long)
    ra_mask[0, 2, 1], rd_mask[0, 2, 3] = 1, 1  # a pedestrian at range bin 2
    ra_mask[0, 5, 4], rd_mask[0, 5, 0] = 3, 3  # a car at range bin 5
    ra_logits = 40.0 * F.one_hot(ra_mask, 4).permute(0, 3, 1, 2).float()
    rd_logits = 40.0 * F.one_hot(rd_mask, 4).permute(0, 3, 1, 2).float()
    assert float(coherence_loss(rd_logits, ra_logits)) == pytest.approx(0.0, abs=1e-12)
    rd_mask[0, 5, 0] = 0  # RD misses the car
    rd_logits = 40.0 * F.one_hot(rd_mask, 4).permute(0, 3, 1, 2).float()
    # range bin 5, car: RD's largest probability 0, RA's 1 (background is 1 in both, elsewhere in RA):
    # one of the 1 x 4 x 8 profile entries differs, by 1
    assert float(coherence_loss(rd_logits, ra_logits)) == pytest.approx(1 / 32, rel=1e-6)


def test_multi_view_loss_combines_as_mvrss():
    torch.manual_seed(0)
    outputs = {"rd": torch.randn(2, 4, 8, 4), "ra": torch.randn(2, 4, 8, 6)}
    masks = {"rd": torch.randint(0, 4, (2, 8, 4)), "ra": torch.randint(0, 4, (2, 8, 6))}
    weights = {"rd": torch.tensor([0.1, 0.2, 0.3, 0.4]), "ra": torch.tensor([0.4, 0.3, 0.2, 0.1])}
    losses = MultiViewLoss(weights)(outputs, masks)
    expected = 5 * coherence_loss(outputs["rd"], outputs["ra"])
    for view in ("rd", "ra"):
        ce = F.cross_entropy(outputs[view], masks[view], weight=weights[view])
        assert float(losses[f"{view}_ce"]) == pytest.approx(float(ce))
        expected = expected + torch.stack([ce, 10 * soft_dice_loss(outputs[view], masks[view])]).mean()
    assert float(losses["total"]) == pytest.approx(float(expected), rel=1e-6)
    single = MultiViewLoss({"ra": weights["ra"]})({"ra": outputs["ra"]}, masks)
    assert "coherence" not in single and set(single) == {"ra_ce", "ra_dice", "total"}
    with pytest.raises(ValueError, match="no class weights"):
        MultiViewLoss({"ra": weights["ra"]})(outputs, masks)


@pytest.mark.parametrize("name", ["tmvanet_tiny", "unet_tiny"])
def test_a_few_steps_reduce_the_loss_on_a_fixed_batch(name):
    torch.manual_seed(0)
    model = create_model(name)
    rd, ra, ad = _views(2, model.n_frames, (16, 16, 8))
    masks = {"rd": torch.zeros(2, 16, 8, dtype=torch.long), "ra": torch.zeros(2, 16, 16, dtype=torch.long)}
    masks["rd"][:, 4:7, 2:4] = 3
    masks["ra"][:, 4:7, 9:12] = 3
    views = ("ra",) if name.startswith("unet") else ("rd", "ra")
    loss_fn = MultiViewLoss({view: class_weights_from_counts([200, 1, 1, 10]) for view in views})
    inputs = (ra[:, -1:],) if name.startswith("unet") else (rd, ra, ad)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    totals = []
    for _ in range(8):
        loss = loss_fn(model(*inputs), masks)["total"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        totals.append(float(loss.detach()))
    assert all(math.isfinite(t) for t in totals)
    assert totals[-1] < 0.85 * totals[0]
