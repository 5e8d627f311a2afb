"""``radarseg models summary``: parameters and MACs of the shipped models, of given checkpoints, and (with
``--preset``) of the registry's full-size models per radar preset.

Dense models (the detector) are counted analytically for their preset's input. Sparse segmenters cost what
their ROI holds: they are counted on the ROI of one simulated frame of their preset (region growing seeded at
the true centres, the preset's default thresholds), whose size is reported beside them. Two counters:
``macs`` (FlopCounterMode's FLOPs / 2) and ``macs_paper`` (transposed convs per output position, the paper's);
they agree on every layer but dense transposed convs, so the table shows the paper's figure only where it
differs.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.capabilities import Stage, dense_input_shapes, stage_of
from models.checkpoint import load_checkpoint
from models.compute import MacRecorder, count_macs, count_params
from models.registry import create_model
from radar.errors import UserError
from radar.region_growing import grow_regions
from radar.roi import roi_points
from radar.simulate import simulate_sequence

DETECTORS = ("centre_detector",)
SEGMENTERS = ("minkunet", "spvcnn")
# The shipped model (README, "The shipped model"), relative to the repository.
SHIPPED = tuple(Path(__file__).resolve().parents[2] / "checkpoints" / name for name in ("detector.pt",
                                                                                            "segmenter.pt"))


@lru_cache(maxsize=4)
def _reference_roi(preset: str, seed: int = 0):
    frame = next(simulate_sequence(preset, 1, seed=seed))
    log_power = frame.log_power()
    seeds = np.array([[o.centre_range_bin, o.centre_angle_bin, o.doppler_bin] for o in frame.objects if o.n_voxels])
    regions = grow_regions(log_power, seeds.reshape(-1, 3), frame.profile)
    return roi_points(regions.voxels, log_power, frame.profile, mean_db=float(log_power.mean()),
                      std_db=float(log_power.std()))


@torch.no_grad()
def _row(model: nn.Module, name: str, preset: str, source: str) -> dict:
    """One row for a built model: a dense model (the detector) on its preset's input, else a sparse
    segmenter on the reference ROI."""
    model = model.eval()
    shapes = dense_input_shapes(model, preset)
    if shapes is not None:
        report = count_macs(model, *shapes)
        return {"model": name, "source": source, "preset": preset, "params": report.params, "macs": report.macs,
                "macs_paper": report.macs_paper, "input": " + ".join("x".join(map(str, s)) for s in shapes)}
    points = _reference_roi(preset)
    coords, feats = torch.from_numpy(points.coords), torch.from_numpy(points.features)
    batch = torch.zeros(len(coords), dtype=torch.int64)
    with MacRecorder(model) as recorder:
        model(model.make_input(torch.cat([batch[:, None], coords], 1), feats))
    report = recorder.report()
    return {"model": name, "source": source, "preset": preset, "params": count_params(model), "macs": report.macs,
            "macs_paper": report.macs_paper, "input": f"{len(points)} ROI voxels (true centres, seed 0)"}


def _shown(path: str | Path) -> str:
    """The path relative to the working directory when under it (no machine paths in printed tables)."""
    try:
        return str(Path(path).resolve().relative_to(Path.cwd()))
    except ValueError:
        return str(path)


def checkpoint_rows(paths: tuple[str | Path, ...]) -> list[dict]:
    """Rows of checkpoint files (the shipped ones by default): the networks as stored, pruning included."""
    rows = []
    for path in paths:
        checkpoint = load_checkpoint(path)
        model = checkpoint.build()
        if stage_of(model) not in (Stage.DETECTOR, Stage.SEGMENTER):
            raise UserError(f"{path}: model {checkpoint.model_name!r}; expected a detector or a sparse segmenter "
                             f"checkpoint (the 2-D baselines are counted by radarseg compare)")
        rows.append(_row(model, checkpoint.model_name, checkpoint.preset, _shown(path)))
    return rows


def models_summary(presets: tuple[str, ...] = (), checkpoints: tuple[str | Path, ...] = SHIPPED) -> list[dict]:
    """Rows ``{model, source, preset, params, macs, macs_paper, input}`` (MACs per frame): the checkpoints
    first, then the registry's full-size models of each preset in ``presets``."""
    rows = checkpoint_rows(checkpoints)
    for preset in presets:
        for name in (*DETECTORS, *SEGMENTERS):
            rows.append(_row(create_model(name, preset=preset), name, preset, "registry (full size, untrained)"))
    return rows


def format_summary(rows: list[dict]) -> str:
    lines = [f"{'model':16} {'preset':8} {'params':>9} {'GMACs':>7} {'(paper)':>8}  input  [source]"]
    for r in rows:
        paper = f"{r['macs_paper'] / 1e9:8.3f}" if r["macs_paper"] != r["macs"] else f"{'same':>8}"
        lines.append(f"{r['model']:16} {r['preset']:8} {r['params'] / 1e6:8.3f}M {r['macs'] / 1e9:7.3f} {paper}  "
                     f"{r['input']}  [{r['source']}]")
    lines.append("GMACs per frame: FlopCounterMode convention (FLOPs / 2); (paper): the paper's counter (transposed "
                 "convs per output position), shown where it differs")
    return "\n".join(lines)
