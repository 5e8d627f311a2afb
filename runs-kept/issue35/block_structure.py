import numpy as np, torch, time, statistics
from models.erasenet.model import EraseNet
from models.sparse import compiled
from radar.simulate import simulate_sequence
torch.set_num_threads(1)
net = EraseNet.from_checkpoints("checkpoints/detector.pt", "checkpoints/segmenter.pt")
maps = {}
orig = compiled.neighbour_conv_fused
def grab(src, nb, w, *r, **k):
    if nb.shape[1] == 27 and nb.shape[0] == src.shape[0]:
        maps.setdefault(src.shape[0], nb.clone())
    return orig(src, nb, w, *r, **k)
compiled.neighbour_conv_fused = grab
for f in list(simulate_sequence("small", 12, seed=5))[-1:]:
    net.segment(f.log_power(), is_log_power=True)
compiled.neighbour_conv_fused = orig
for n in sorted(maps, reverse=True)[:3]:
    nb = maps[n].numpy(); present = nb < n
    B = 64
    nblk = (n + B - 1) // B
    pad = np.zeros((nblk * B, 27), bool); pad[:n] = present
    counts = pad.reshape(nblk, B, 27).sum(1)  # (blocks, 27)
    groups = np.ceil(counts / 8).sum()
    per_offset = present.mean(0)
    src = torch.randn(n, 32); w = torch.randn(27, 32, 32) / 32
    ts = []
    for i in range(11):
        s = time.perf_counter(); orig(src, maps[n], w); ts.append(time.perf_counter() - s)
    t = statistics.median(ts[1:])
    print(n, "pairs/voxel %.1f" % present.sum(1).mean(), "rows per 8-row group %.2f" % (present.sum() / groups),
          "empty (block,offset) %.2f" % (counts == 0).mean(), "offset fill min/max %.2f/%.2f" % (per_offset.min(), per_offset.max()),
          "32ch %.1f GMAC/s" % (present.sum() * 1024 / t / 1e9))
import resource
for n in sorted(maps, reverse=True)[:2]:
    src = torch.randn(n, 32); w = torch.randn(27, 32, 32) / 32
    for i in range(3): orig(src, maps[n], w)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt; s = time.perf_counter()
    for i in range(10): orig(src, maps[n], w)
    t = (time.perf_counter() - s) / 10
    f1 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    print(n, "minor faults per call", (f1 - f0) / 10, "ms per call %.2f" % (1e3 * t))
