import resource
import statistics
import time

import numpy as np
import torch

from benchmarks.frame_profile import submanifold_maps
from models.erasenet.model import EraseNet
from models.sparse import compiled
from radar.simulate import simulate_sequence

torch.set_num_threads(1)
net = EraseNet.from_checkpoints("checkpoints/detector.pt", "checkpoints/segmenter.pt")
maps = submanifold_maps(net, list(simulate_sequence("small", 12, seed=5))[-1].log_power())
orig = compiled.neighbour_conv_fused
for n in sorted(maps, reverse=True)[:3]:
    nb = maps[n].numpy()
    present = nb < n
    B = 64
    nblk = (n + B - 1) // B
    pad = np.zeros((nblk * B, 27), bool)
    pad[:n] = present
    counts = pad.reshape(nblk, B, 27).sum(1)  # (blocks, 27)
    groups = np.ceil(counts / 8).sum()
    per_offset = present.mean(0)
    src = torch.randn(n, 32)
    w = torch.randn(27, 32, 32) / 32
    ts = []
    for _i in range(11):
        s = time.perf_counter()
        orig(src, maps[n], w)
        ts.append(time.perf_counter() - s)
    t = statistics.median(ts[1:])
    print(
        n,
        f"pairs/voxel {present.sum(1).mean():.1f}",
        "rows per 8-row group %.2f" % (present.sum() / groups),
        f"empty (block,offset) {(counts == 0).mean():.2f}",
        f"offset fill min/max {per_offset.min():.2f}/{per_offset.max():.2f}",
        "32ch %.1f GMAC/s" % (present.sum() * 1024 / t / 1e9),
    )

for n in sorted(maps, reverse=True)[:2]:
    src = torch.randn(n, 32)
    w = torch.randn(27, 32, 32) / 32
    for _i in range(3):
        orig(src, maps[n], w)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    s = time.perf_counter()
    for _i in range(10):
        orig(src, maps[n], w)
    t = (time.perf_counter() - s) / 10
    f1 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    print(n, "minor faults per call", (f1 - f0) / 10, "ms per call %.2f" % (1e3 * t))
