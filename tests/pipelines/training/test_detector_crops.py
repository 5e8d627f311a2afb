"""Crop training of the detector: windows' targets are the whole frame's cut, the sampler keeps its object share,
and a detector trained on windows runs on whole frames."""

import json

import numpy as np
import pytest
import torch

from models.checkpoint import load_checkpoint
from models.detector.targets import build_centre_targets, crop_centre_targets
from models.registry import create_model
from pipelines.cli import main as cli
from pipelines.datasets.store import StoreDataset
from pipelines.training.windows import WindowDataset, WindowSampler, whole_frame_batch_norms


def _targets_of(centres: np.ndarray, grid: tuple[int, int]):
    return build_centre_targets([centres], grid)


@pytest.mark.parametrize("origin", [(0, 0), (3, 5), (16, 0), (12, 20)])
def test_a_windows_targets_are_that_window_of_the_whole_frames(origin):
    grid, cells = (128, 128), (16, 12)  # bins; window in output cells
    centres = np.array([[13.0, 22.5, 4.0], [70.2, 90.9, 10.0], [60.0, 40.0, 3.0], [2.0, 125.0, 1.0]])
    whole = _targets_of(centres, grid)
    cut = crop_centre_targets(whole, [origin], cells)
    r, a = origin
    h, w = cells
    assert torch.equal(cut["heatmap"], whole["heatmap"][..., r:r + h, a:a + w])
    # each object whose centre cell is inside keeps its targets, its index on the window's grid at its peak
    inside = [(4 * r <= c[0] < 4 * (r + h)) and (4 * a <= c[1] < 4 * (a + w)) for c in centres]
    assert cut["mask"][0].tolist()[:len(centres)] == inside
    assert any(inside) or origin == (16, 0)
    for k in np.flatnonzero(inside):
        row, col = divmod(int(cut["indices"][0, k]), w)
        assert (row + r, col + a) == divmod(int(whole["indices"][0, k]), grid[1] // 4)
        assert cut["heatmap"][0, 0, row, col] == 1.0
        assert torch.allclose(cut["offsets"][0, k], whole["offsets"][0, k])
        assert cut["doppler"][0, k] == whole["doppler"][0, k]


def test_a_window_of_the_whole_grid_leaves_the_targets_unchanged():
    whole = _targets_of(np.array([[40.0, 60.0, 2.0]]), (64, 96))
    cut = crop_centre_targets(whole, [(0, 0)], (16, 24))
    for name in ("heatmap", "indices", "offsets", "doppler", "mask"):
        assert torch.equal(cut[name], whole[name]), name


def test_a_window_that_does_not_fit_is_refused():
    whole = _targets_of(np.array([[40.0, 60.0, 2.0]]), (64, 64))
    with pytest.raises(ValueError, match="does not fit"):
        crop_centre_targets(whole, [(10, 0)], (8, 8))


def test_the_sampler_draws_windows_with_an_object_at_its_share():
    sampler = WindowSampler((64, 128), (256, 256), object_share=0.7)
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(2000):
        centres = rng.uniform(0, 255, size=(int(rng.integers(1, 4)), 3))
        window = sampler.draw(centres, rng)
        cells = np.floor(centres[:, :2] / 4)
        r, a = window.range_start // 4, window.angle_start // 4
        holds = bool(np.any((cells[:, 0] >= r) & (cells[:, 0] < r + 16) & (cells[:, 1] >= a) & (cells[:, 1] < a + 32)))
        assert holds == window.holds_object  # what the sampler says is what the window holds
        assert 0 <= window.range_start <= 192 and 0 <= window.angle_start <= 128
        assert window.range_start % 4 == 0 and window.angle_start % 4 == 0
        draws.append(holds)
    share = np.mean(draws)
    assert abs(share - 0.7) < 3 * np.sqrt(0.7 * 0.3 / len(draws)), share


def test_the_sampler_gives_clutter_windows_on_a_frame_without_objects():
    sampler = WindowSampler((32, 32), (128, 128), object_share=1.0)
    window = sampler.draw(np.zeros((0, 3)), np.random.default_rng(1))
    assert not window.holds_object


@pytest.mark.parametrize("size", [(30, 64), (64, 0), (256, 64)])
def test_a_window_size_off_the_stride_or_the_grid_is_refused(size):
    with pytest.raises(ValueError, match="multiple of 4"):
        WindowSampler(size, (128, 128))


def test_windows_of_frames_read_in_the_stored_layout_are_the_same(small_store):
    stored = StoreDataset(small_store, "train", fields=("input", "objects"), normalise=False, flip_prob=0.5,
                          doppler_last=True)
    model_layout = StoreDataset(small_store, "train", fields=("input", "objects"), normalise=False, flip_prob=0.5)
    sampler = WindowSampler((32, 64), (128, 128))
    windows = [WindowDataset(frames, sampler, seed=5) for frames in (stored, model_layout)]
    for a, b in zip(*([w[i] for i in range(len(w))] for w in windows), strict=True):
        assert torch.equal(a["window_origin"], b["window_origin"]) and a["flipped"] == b["flipped"]
        assert torch.equal(a["input"], b["input"]) and a["input"].shape == (32, 32, 64)


def test_window_samples_cut_the_input_and_keep_the_object_table(small_store):
    frames = StoreDataset(small_store, "train", fields=("input", "objects"), normalise=False)
    windows = WindowDataset(frames, WindowSampler((32, 64), (128, 128)), seed=3)
    whole, cut = frames[0], windows[0]
    r, a = cut["window_origin"].tolist()
    assert cut["input"].shape == (32, 32, 64)
    assert torch.equal(cut["input"], whole["input"][:, r:r + 32, a:a + 64])
    assert torch.equal(torch.nan_to_num(cut["objects"]), torch.nan_to_num(whole["objects"]))
    first = [windows[i]["window_origin"].tolist() for i in range(len(windows))]
    assert first == [windows[i]["window_origin"].tolist() for i in range(len(windows))]  # reproducible
    windows.set_epoch(1)
    assert first != [windows[i]["window_origin"].tolist() for i in range(len(windows))]  # another epoch, other windows


def test_a_detector_reads_the_cartesian_channels_of_its_window():
    detector = create_model("centre_detector_tiny", preset="small").eval()
    frame = torch.randn(1, 32, 128, 128)
    with torch.no_grad():
        whole = detector(frame)["heatmap_logits"]
        # the same window at two places of the grid: only the Cartesian channels differ, so the outputs do
        left = detector(frame[..., :64, :64], window_origins=torch.tensor([[0, 0]]))["heatmap_logits"]
        right = detector(frame[..., :64, :64], window_origins=torch.tensor([[64, 64]]))["heatmap_logits"]
    assert left.shape == (1, 1, 16, 16) and whole.shape == (1, 1, 32, 32)
    assert (left - right).abs().max() > 0
    with pytest.raises(ValueError, match="multiple of 4"):
        detector(frame[..., :64, :64], window_origins=torch.tensor([[2, 0]]))
    with pytest.raises(ValueError, match="expected log power"):
        detector(frame[..., :64, :64])  # a window without its place is refused


def test_a_crop_trained_detector_gives_whole_frame_outputs(small_store, tmp_path):
    run = tmp_path / "det"
    assert cli(["train", "detector", "--store", str(small_store), "--out", str(run), "--model",
                "centre_detector_tiny", "--crop", "32", "64", "--batch-size", "2", "--max-steps", "2",
                "--no-progress"]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["crop"] == [32, 64] and config["resolved"]["crop"] == [32, 64]
    last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
    assert 0.0 <= last["val_mAP"] <= 1.0  # validated on whole frames
    detector = load_checkpoint(run / "model.pt").build().eval()
    with torch.no_grad():
        outputs = detector(torch.zeros(2, 32, 128, 128))
    assert outputs["heatmap_logits"].shape == (2, 1, 32, 32)
    assert outputs["offset"].shape == (2, 2, 32, 32)


def test_a_crop_for_another_stage_or_off_the_grid_is_refused(small_store, tmp_path):
    assert cli(["train", "detector", "--store", str(small_store), "--out", str(tmp_path / "a"), "--model",
                "centre_detector_tiny", "--crop", "30", "64", "--max-steps", "1", "--no-progress"]) == 2
    assert not (tmp_path / "a").exists()


class _ConvNorm(torch.nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 1)
        self.norm = torch.nn.BatchNorm2d(4, momentum=0.3)

    def forward(self, log_power):
        return self.norm(self.conv(log_power))


def test_whole_frame_batch_norms_take_the_frames_statistics_and_leave_the_weights():
    torch.manual_seed(0)
    model = _ConvNorm().eval()
    weights = {k: v.clone() for k, v in model.state_dict().items() if "running" not in k and "num_batches" not in k}
    batches = [{"log_power": torch.randn(2, 3, 8, 8) * 3 + 1} for _ in range(3)]
    assert whole_frame_batch_norms(model, batches) == 6
    with torch.no_grad():
        features = torch.cat([model.conv(b["log_power"]) for b in batches])  # (6, 4, 8, 8)
    per_batch = [model.conv(b["log_power"]).detach() for b in batches]
    assert torch.allclose(model.norm.running_mean, features.mean(dim=(0, 2, 3)), atol=1e-5)
    expected_var = torch.stack([f.var(dim=(0, 2, 3), unbiased=True) for f in per_batch]).mean(0)
    assert torch.allclose(model.norm.running_var, expected_var, atol=1e-4)
    assert model.norm.momentum == 0.3 and not model.training
    for name, value in weights.items():
        assert torch.equal(model.state_dict()[name], value), name
