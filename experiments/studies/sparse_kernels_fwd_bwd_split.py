"""Forward and backward apart: sparse 3^3 32->32 (compiled engine) and dense Conv3d on the benchmark's blobs."""

import json
import os
import sys

import torch
from torch import nn

from benchmarks.sparse_conv import LAYOUTS
from benchmarks.timing import time_call
from models.sparse import SparseTensor, SubmanifoldConv3d

torch.set_num_threads(1)
out = {}
for n in (20000, 100000):
    g = torch.Generator().manual_seed(0)
    coords = LAYOUTS["blobs"](n, 0.05, g)
    grid = [int(v) + 1 for v in coords[:, 1:].max(dim=0).values]
    feats = torch.randn(n, 32, generator=g).requires_grad_(True)
    conv = SubmanifoldConv3d(32, 32)
    x = SparseTensor(coords, feats)
    x.cache.kernel_map(1, 3, 1)
    dconv = nn.Conv3d(32, 32, 3, padding=1, bias=False)
    dinp = torch.randn(1, 32, *grid, generator=g).requires_grad_(True)

    def t(fn, r):
        return time_call(fn, r)["median_s"]

    def sf(conv=conv, x=x):
        with torch.no_grad():
            conv(x)

    def sfb(conv=conv, x=x):
        conv(x).feats.sum().backward()

    def df(dconv=dconv, dinp=dinp):
        with torch.no_grad():
            dconv(dinp)

    def dfb(dconv=dconv, dinp=dinp):
        dconv(dinp).sum().backward()

    r = {
        "sparse_fwd": t(sf, 7),
        "sparse_fwd_bwd": t(sfb, 7),
        "dense_fwd": t(df, 2),
        "dense_fwd_bwd": t(dfb, 2),
        "sparse_macs_fwd": conv.last_macs,
        "dense_macs_fwd": grid[0] * grid[1] * grid[2] * 27 * 32 * 32,
    }
    r["sparse_bwd"] = r["sparse_fwd_bwd"] - r["sparse_fwd"]
    r["dense_bwd"] = r["dense_fwd_bwd"] - r["dense_fwd"]
    for k in ("fwd", "bwd"):
        m = 1 if k == "fwd" else 2
        r[f"sparse_{k}_gmacs"] = m * r["sparse_macs_fwd"] / r[f"sparse_{k}"] / 1e9
        r[f"dense_{k}_gmacs"] = m * r["dense_macs_fwd"] / r[f"dense_{k}"] / 1e9
    r["ratio_fwd"] = r["dense_fwd"] / r["sparse_fwd"]
    r["ratio_bwd"] = r["dense_bwd"] / r["sparse_bwd"]
    r["ratio_fwd_bwd"] = r["dense_fwd_bwd"] / r["sparse_fwd_bwd"]
    r["mac_ratio"] = r["dense_macs_fwd"] / r["sparse_macs_fwd"]
    out[n] = r
    print(n, {k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()}, flush=True)
out["load"] = os.getloadavg()
json.dump(out, open(sys.argv[1], "w"), indent=1)
