"""Experiment: per-class logit offsets on the segmenter's voxel logits before argmax, swept on one store.

For every frame: the shipped pair's seeds (with history as evaluate), the segmenter's voxel logits kept; then for
each offset vector, the classes, RA/RD projections and the confusion against the store's masks.
"""

import argparse
import itertools
import json
import sys

import numpy as np
import torch

from models.checkpoint import load_checkpoint
from models.erasenet.model import EraseNet
from models.runtime import load_erasenet
from pipelines.datasets.history import earlier_frames, earlier_slots
from pipelines.datasets.store import open_store  # noqa
from pipelines.evaluation.scoring import ViewConfusion
from radar import transforms
from radar.input_kind import InputKind

parser = argparse.ArgumentParser()
parser.add_argument("--store", required=True)
parser.add_argument("--detector", default="checkpoints/detector.pt")
parser.add_argument("--segmenter", default="checkpoints/segmenter.pt")
parser.add_argument("--ped", type=float, nargs="+", default=[-1.5, -1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5])
parser.add_argument("--cyc", type=float, nargs="+", default=[-0.5, 0.0, 0.5])
parser.add_argument("--car", type=float, nargs="+", default=[0.0])
parser.add_argument("--max-frames", type=int, default=0)
parser.add_argument("--out", required=True)
args = parser.parse_args()
torch.set_num_threads(1)

captured = {}


def _segment_voxels(self, regions, log_power):
    classes, macs, executed = EraseNet._segment_voxels(self, regions, log_power)
    return classes, macs, executed


orig_argmax = torch.Tensor.argmax


def capture_argmax(self, *a, **k):
    captured["logits"] = self.detach().clone()
    return orig_argmax(self, *a, **k)


net = load_erasenet(load_checkpoint(args.detector), load_checkpoint(args.segmenter))
root = open_store(args.store)
arrays = {n: root[n] for n in ("input", "ra_mask", "rd_mask")}
n = root["input"].shape[0]
slots = np.arange(n) if not args.max_frames else np.linspace(0, n - 1, args.max_frames).astype(int)
earlier = earlier_slots(root, net.history_frames) if net.history_frames else None
grid = list(itertools.product(args.ped, args.cyc, args.car))
confusions = {g: ViewConfusion(net.profile.num_classes) for g in grid}
shape, ncls = net.profile.shape, net.profile.num_classes

for i, slot in enumerate(slots):
    lp = arrays["input"][int(slot)].astype(np.float32)
    history = None if earlier is None else earlier_frames(arrays["input"], earlier[slot])
    captured.clear()
    torch.Tensor.argmax = capture_argmax
    try:
        result = net.segment(lp, kind=InputKind.log_power, history=history)
    finally:
        torch.Tensor.argmax = orig_argmax
    truth = {"ra": arrays["ra_mask"][int(slot)], "rd": arrays["rd_mask"][int(slot)]}
    voxels = result.regions.voxels
    if len(voxels) == 0:
        for g in grid:
            confusions[g].add_masks(truth, result.ra_mask, result.rd_mask)
        continue
    # logits are per unique point; map back with the inverse used by _segment_voxels
    from radar.roi import roi_points

    points = roi_points(voxels, lp, net.profile, mean_db=net.mean_db, std_db=net.std_db)
    logits = captured["logits"].numpy()
    base = logits.argmax(1)[points.inverse]
    ok = np.array_equal(base.astype(np.uint8), result.labels[tuple(voxels.T)])
    if not ok:
        print("mismatch at", slot, file=sys.stderr)
    for g in grid:
        off = np.array([0.0, *g], np.float32)
        cls = (logits + off).argmax(1).astype(np.uint8)[points.inverse]
        ra = transforms.project_voxels(voxels, cls, shape, 2, ncls)
        rd = transforms.project_voxels(voxels, cls, shape, 1, ncls)
        confusions[g].add_masks(truth, ra, rd)
    if i % 24 == 0:
        print(i, len(slots), file=sys.stderr, flush=True)

rows = []
for g in grid:
    s = confusions[g].summary(net.class_names)
    rows.append(
        {
            "offsets": g,
            "ra_miou": s["ra"]["mIoU"],
            "rd_miou": s["rd"]["mIoU"],
            "ra_iou": s["ra"]["iou"],
            "rd_iou": s["rd"]["iou"],
        }
    )
    print(
        g,
        f"RA {100 * s['ra']['mIoU']:.2f} RD {100 * s['rd']['mIoU']:.2f} ped {100 * s['ra']['iou']['pedestrian']:.1f}/"
        f"{100 * s['rd']['iou']['pedestrian']:.1f} cyc {100 * s['ra']['iou']['cyclist']:.1f}/"
        f"{100 * s['rd']['iou']['cyclist']:.1f}"
        f" car {100 * s['ra']['iou']['car']:.1f}/{100 * s['rd']['iou']['car']:.1f}",
    )
json.dump(rows, open(args.out, "w"), indent=1)
