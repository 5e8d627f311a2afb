"""The segmenter's seed jitter is measured on the seeds EraseNet grows from: Doppler refined from the cube."""

import numpy as np
import pytest
import torch

import pipelines.training.jitter as jitter
from pipelines.datasets.spread import subset
from pipelines.datasets.store import StoreDataset
from pipelines.evaluation.scoring import frame_centres
from radar.profiles import get_profile


class OffsetTruthDecoder:
    """A detector that finds every object of the split exactly but reads its Doppler ``offset`` bins high;
    frames decoded in the order measure_detector_errors reads them."""

    def __init__(self, store, split: str, offset: float):
        dataset = StoreDataset(store, split, fields=("objects",), normalise=False)
        self.queue = [frame_centres(dataset[i]) for i in subset(len(dataset), 0)]
        self.offset = offset

    def __call__(self, x: torch.Tensor) -> dict[str, int]:
        return {"frames": len(x)}

    def decode(self, outputs, k, score_threshold):  # noqa: ANN001, ANN201 (the detector's decode contract)
        frames = []
        for _ in range(outputs["frames"]):
            bins = self.queue.pop(0)
            frames.append({"score": np.full(len(bins), 0.9), "range_bin": bins[:, 0], "angle_bin": bins[:, 1],
                           "doppler_bin": bins[:, 2] + self.offset})
        return frames


class FakeCheckpoint:
    preset = "small"
    profile = get_profile("small")
    normalisation = {"mean": 60.0, "std": 8.0}

    def __init__(self, decoder: OffsetTruthDecoder):
        self.decoder = decoder

    def build(self, device="cpu"):  # noqa: ANN001, ANN201
        return self.decoder


def _doppler_residual(store, monkeypatch, **kwargs) -> float:
    monkeypatch.setattr(jitter, "load_checkpoint", lambda path: FakeCheckpoint(OffsetTruthDecoder(store, "train", 1.5)))
    measured = jitter.measure_detector_errors("unused.pt", store, "train", **kwargs)
    return float(np.mean(np.abs(measured.residuals[:, 2])))


def test_doppler_residual_shrinks_with_the_refinement(small_store, monkeypatch):
    raw = _doppler_residual(small_store, monkeypatch, doppler_refinement=None)
    refined = _doppler_residual(small_store, monkeypatch)
    assert raw == pytest.approx(1.5)
    assert refined < 0.7 * raw, (raw, refined)
