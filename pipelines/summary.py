"""``radarseg models summary``: parameters and MACs of every model per radar preset.

Dense models are counted analytically for the preset's input. Sparse segmenters cost what their ROI
holds: they are counted on the ROI of one simulated frame (region growing seeded at the true centres,
the preset's default thresholds), whose size is reported beside them.
"""

from __future__ import annotations

import numpy as np
import torch

from models.compute import MacRecorder, count_macs, count_params
from models.registry import create_model
from models.segmenter.spvcnn import SPVCNN, PointTensor
from models.sparse import SparseTensor
from radar.profiles import get_profile
from radar.region_growing import grow_regions
from radar.roi import roi_points
from radar.simulate import simulate_sequence

DETECTORS = ("centre_detector",)
SEGMENTERS = ("minkunet", "spvcnn")


def _reference_roi(preset: str, seed: int = 0):
    frame = list(simulate_sequence(preset, 1, seed=seed))[0]
    log_power = frame.log_power()
    seeds = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels])
    regions = grow_regions(log_power, seeds.reshape(-1, 3), frame.profile)
    return roi_points(regions.voxels, log_power, frame.profile, mean_db=float(log_power.mean()),
                      std_db=float(log_power.std()))


@torch.no_grad()
def models_summary(presets: tuple[str, ...] = ("small", "carrada", "nxp")) -> list[dict]:
    """Rows ``{model, preset, params, macs, macs_paper, input}`` (MACs per frame)."""
    rows = []
    for preset in presets:
        n_range, n_angle, n_doppler = get_profile(preset).shape
        for name in DETECTORS:
            report = count_macs(create_model(name, preset=preset), (1, n_doppler, n_range, n_angle))
            rows.append({"model": name, "preset": preset, "params": report.params, "macs": report.macs,
                         "macs_paper": report.macs_paper, "input": f"1x{n_doppler}x{n_range}x{n_angle}"})
        points = _reference_roi(preset)
        coords = torch.from_numpy(points.coords)
        feats = torch.from_numpy(points.features)
        batch = torch.zeros(len(coords), dtype=torch.int64)
        for name in SEGMENTERS:
            model = create_model(name, preset=preset).eval()
            with MacRecorder(model) as recorder:
                if isinstance(model, SPVCNN):
                    model(PointTensor(batch, coords.float() + 0.5, feats))
                else:
                    model(SparseTensor(torch.cat([batch[:, None], coords], 1), feats))
            report = recorder.report()
            rows.append({"model": name, "preset": preset, "params": count_params(model), "macs": report.macs,
                         "macs_paper": report.macs_paper, "input": f"{len(points)} ROI voxels"})
    return rows


def format_summary(rows: list[dict]) -> str:
    lines = [f"{'model':18} {'preset':8} {'params':>10} {'GMACs':>8} {'GMACs (paper)':>14}  input"]
    for r in rows:
        lines.append(f"{r['model']:18} {r['preset']:8} {r['params'] / 1e6:9.3f}M {r['macs'] / 1e9:8.3f} "
                     f"{r['macs_paper'] / 1e9:14.3f}  {r['input']}")
    lines.append("GMACs: FlopCounterMode convention (FLOPs / 2); paper: transposed convs counted per output position")
    return "\n".join(lines)
