import statistics
import time

import torch

from benchmarks.frame_profile import submanifold_maps
from models.erasenet.model import EraseNet
from models.sparse import compiled
from radar.simulate import simulate_sequence

torch.set_num_threads(1)
t0 = time.time()
mod = compiled.load()
print("load %.1f s" % (time.time() - t0), flush=True)
net = EraseNet.from_checkpoints("checkpoints/detector.pt", "checkpoints/segmenter.pt")
maps = submanifold_maps(net, list(simulate_sequence("small", 12, seed=5))[-1].log_power())
orig = compiled.neighbour_conv_fused
for n in sorted(maps, reverse=True)[:2]:
    nb = maps[n]
    pairs = int((nb < n).sum())
    for c in (8, 16, 24, 32, 64):
        src = torch.randn(n, c)
        w = torch.randn(27, c, c) / c
        a = mod.neighbour_conv_fused(src, nb, w, None, None, False)
        b = mod.neighbour_conv_fused_packed(src, nb, w, None, None, False)
        assert torch.equal(a, b)
        ts = {"plain": [], "packed": []}
        for i in range(12):
            for name, fn in (("plain", mod.neighbour_conv_fused), ("packed", mod.neighbour_conv_fused_packed)):
                s = time.perf_counter()
                fn(src, nb, w, None, None, False)
                e = time.perf_counter() - s
                if i > 1:
                    ts[name].append(e)
        m = {k: statistics.median(v) for k, v in ts.items()}
        print(
            n,
            c,
            " ".join(f"{k} {pairs * c * c / v / 1e9:.1f} GMAC/s" for k, v in m.items()),
            "packed/plain time %.2f" % (m["packed"] / m["plain"]),
            flush=True,
        )
