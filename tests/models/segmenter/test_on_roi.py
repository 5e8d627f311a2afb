"""Both segmenters overfit one simulated ROI: stage 2 can learn the simulator's labels."""

import numpy as np
import pytest
import torch

from models.registry import create_model
from models.segmenter.spvcnn import PointTensor
from models.sparse import SparseTensor
from radar.region_growing import RegionGrowingConfig, grow_regions
from radar.roi import roi_points
from radar.simulate import simulate_sequence


@pytest.fixture(scope="module")
def roi_batch():
    frame = list(simulate_sequence("small", 2, seed=3))[1]
    lp = frame.log_power()
    obj = max(frame.objects, key=lambda o: o.n_voxels)
    seed = np.array([[obj.centre_range_bin, obj.centre_angle_bin, obj.doppler_bin]])
    # a compact ROI around one object keeps the test fast
    config = RegionGrowingConfig.for_profile("small", distance_m=4.0, bridge=False)
    regions = grow_regions(lp, seed, frame.profile, config)
    points = roi_points(regions.voxels, lp, frame.profile, mean_db=60.0, std_db=8.0)
    target = torch.from_numpy(frame.labels[tuple(regions.voxels.T)].astype(np.int64))
    assert len(target) < 6000
    assert 0.01 < (target > 0).float().mean() < 0.9, "the ROI should mix object and background voxels"
    return points, target


@pytest.mark.parametrize("name", ["minkunet_tiny", "spvcnn_tiny"])
def test_segmenter_overfits_a_simulated_roi(roi_batch, name):
    points, target = roi_batch
    torch.manual_seed(0)
    model = create_model(name, preset="small")
    coords = torch.from_numpy(points.coords)
    feats = torch.from_numpy(points.features)
    batch = torch.zeros(len(coords), dtype=torch.int64)
    inputs = (PointTensor(batch, coords.float() + 0.5, feats) if name.startswith("spvcnn")
              else SparseTensor(torch.cat([batch[:, None], coords], 1), feats))
    optimiser = torch.optim.Adam(model.parameters(), lr=0.02)
    counts = torch.bincount(target, minlength=4).float()
    weights = torch.where(counts > 0, counts.sum() / counts.clamp(min=1), torch.zeros(()))
    losses = []
    for _ in range(40):
        loss = torch.nn.functional.cross_entropy(model(inputs), target, weight=weights)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    with torch.no_grad():  # batch statistics, as in training: 40 steps barely move BN running averages
        predicted = model(inputs).argmax(1)
    assert losses[-1] < 0.3 * losses[0]
    # the ROI is mostly background: check each side, not plain accuracy
    assert (predicted[target > 0] == target[target > 0]).float().mean() > 0.9
    assert (predicted[target == 0] == 0).float().mean() > 0.95
