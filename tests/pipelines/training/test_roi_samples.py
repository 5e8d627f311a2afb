"""The segmenter's ROI samples read the store's (R, A, D) log power as stored: the same ROIs as from the model's
(D, R, A) layout transposed back, flipped or not."""

import numpy as np
import torch

from pipelines.datasets.store import StoreDataset
from pipelines.datasets.store_info import StoreInfo
from pipelines.evaluation.scoring import frame_centres
from pipelines.training.segmenter import RoiDataset
from radar.region_growing import grow_regions
from radar.roi import roi_points


def test_roi_samples_equal_those_grown_from_the_transposed_cube(small_store):
    store = StoreInfo.read(small_store)
    rois = RoiDataset(store, "train", None, flip_prob=0.5, seed=4)
    frames = StoreDataset(small_store, "train", fields=("input", "labels", "objects"), normalise=False,
                          flip_prob=0.5, seed=4)
    flipped = 0
    for item in range(len(rois)):
        sample = frames[rois.indices[item]]
        flipped += sample["flipped"]
        log_power = np.ascontiguousarray(sample["input"].permute(1, 2, 0).numpy())  # (R, A, D)
        regions = grow_regions(log_power, frame_centres(sample), store.profile)
        voxels = regions.voxels if len(regions) else regions.seeds
        points = roi_points(voxels, log_power, store.profile, mean_db=store.normalisation["mean"],
                            std_db=store.normalisation["std"])
        roi = rois[item]
        assert torch.equal(roi["coords"], torch.from_numpy(points.coords))
        assert torch.equal(roi["features"], torch.from_numpy(points.features))
        assert torch.equal(roi["labels"], torch.from_numpy(sample["labels"].numpy()[tuple(voxels.T)].astype(np.int64)))
    assert len(rois) >= 2
