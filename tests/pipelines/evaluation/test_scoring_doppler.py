"""Detection AP is scored on the Doppler the product outputs: refined from the cube (radar.doppler)."""

import numpy as np
import torch
from torch import nn

from pipelines.datasets.spread import subset
from pipelines.datasets.store import StoreDataset
from pipelines.evaluation.scoring import frame_centres, score_detector
from radar.profiles import SMALL


class OffsetTruthDetector(nn.Module):
    """Decodes each frame's true centres, in the order ``score_detector`` reads them, with every Doppler
    ``offset`` bins off (a detector that finds objects exactly but mis-reads their Doppler)."""

    def __init__(self, centres: list[np.ndarray], offset: float):
        super().__init__()
        self.queue = [c.copy() for c in centres]
        self.offset = offset

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"batch": torch.zeros(len(x))}

    def decode(self, outputs, k, score_threshold):  # noqa: ANN001, ANN201 (the detector's decode contract)
        frames = []
        for _ in range(len(outputs["batch"])):
            bins = torch.from_numpy(self.queue.pop(0))
            frames.append({"score": torch.linspace(0.9, 0.5, len(bins)), "range_bin": bins[:, 0],
                           "angle_bin": bins[:, 1], "doppler_bin": (bins[:, 2] + self.offset) % SMALL.n_doppler})
        return frames


def _detector(store, offset):
    dataset = StoreDataset(store, "train", fields=("objects",), normalise=False)
    return OffsetTruthDetector([frame_centres(dataset[i]) for i in subset(len(dataset), 0)], offset)


def test_ap_at_1_counts_a_doppler_the_cube_corrects(small_store):
    normalisation = {"mean": 60.0, "std": 8.0}
    raw = score_detector(_detector(small_store, 1.5), str(small_store), "train", SMALL, normalisation,
                         doppler_refinement=None)
    refined = score_detector(_detector(small_store, 1.5), str(small_store), "train", SMALL, normalisation)
    exact = score_detector(_detector(small_store, 0.0), str(small_store), "train", SMALL, normalisation,
                           doppler_refinement=None)
    assert exact["AP@1"] > 0.9  # exact centres: the stub and the scorer agree on frames and order
    assert raw["AP@1"] == 0.0  # 1.5 bins off: no match at k = 1
    assert refined["AP@1"] > 0.3, refined  # 0.46 measured on this store
