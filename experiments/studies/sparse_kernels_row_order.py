"""Does the stride-1 rate depend on row locality? The compiled 3^3 kernel on a frame's stride-1 map in three row
orders: as built (sorted by (batch, x, y, z)), reverse Cuthill-McKee of the neighbour graph, and random; interleaved."""

import json
import os
import statistics
import sys
import time

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import reverse_cuthill_mckee

from benchmarks.frame_profile import submanifold_maps
from models.erasenet.model import EraseNet
from models.sparse import compiled
from radar.simulate import simulate_sequence

torch.set_num_threads(1)
net = EraseNet.from_checkpoints("checkpoints/detector.pt", "checkpoints/segmenter.pt")
maps = submanifold_maps(net, list(simulate_sequence("small", 4, seed=5))[-1].log_power())
orig = compiled.neighbour_conv_fused
n = max(maps)
nb = maps[n].numpy()
rows, cols = np.nonzero(nb < n)
adj = sp.csr_matrix((np.ones(len(rows)), (rows, nb[rows, cols])), shape=(n, n))


def permuted(perm):
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    table = nb[perm]
    table = np.where(table < n, inv[np.minimum(table, n - 1)], n)
    return torch.from_numpy(np.ascontiguousarray(table))


def bandwidth(table):
    t = table.numpy()
    r, c = np.nonzero(t < n)
    return float(np.median(np.abs(t[r, c] - r)))


orders = {
    "sorted": torch.from_numpy(nb),
    "rcm": permuted(np.asarray(reverse_cuthill_mckee(adj, symmetric_mode=True))),
    "random": permuted(np.random.default_rng(0).permutation(n)),
}
out = {"voxels": n, "median_index_distance": {k: bandwidth(v) for k, v in orders.items()}, "rows": []}
for width in (8, 24, 32, 64):
    src = torch.randn(n, width)
    w = torch.randn(27, width, width) / width
    times = {k: [] for k in orders}
    for r in range(11):
        for k, table in orders.items():
            s = time.perf_counter()
            orig(src, table, w)
            e = time.perf_counter() - s
            if r:
                times[k].append(e)
    pairs = int((nb < n).sum())
    row = {
        "channels": width,
        **{f"{k}_ms": 1e3 * statistics.median(v) for k, v in times.items()},
        **{f"{k}_gmacs": pairs * width * width / statistics.median(v) / 1e9 for k, v in times.items()},
    }
    out["rows"].append(row)
    print({k: round(v, 2) for k, v in row.items()}, flush=True)
out["load"] = os.getloadavg()
print(out["median_index_distance"], out["load"])
json.dump(out, open(sys.argv[1], "w"), indent=1)
