"""Pictures of radar frames: RA and RD views with the labels drawn over them."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402

from radar import transforms  # noqa: E402
from radar.frame import RadarFrame  # noqa: E402

CLASS_COLOURS = ["#00000000", "#ff4040", "#40c0ff", "#ffd000", "#60ff60"]


def _overlay(ax, mask: np.ndarray, extent, num_classes: int) -> None:
    cmap = ListedColormap(CLASS_COLOURS[:num_classes])
    ax.imshow(np.ma.masked_equal(mask, 0), origin="lower", aspect="auto", extent=extent, cmap=cmap,
              vmin=0, vmax=num_classes - 1, alpha=0.45, interpolation="nearest")
    for c in range(1, num_classes):
        if (mask == c).any():
            ax.contour((mask == c).astype(float), levels=[0.5], colors=[CLASS_COLOURS[c][:7]], linewidths=0.8,
                       origin="lower", extent=extent)


def plot_frame_views(frame: RadarFrame, path: str | Path, *, title: str | None = None) -> Path:
    """Write a PNG with the RA view (angle x range) and the RD view (velocity x range) of ``frame``,
    label masks and object names drawn over them. Axes in degrees-as-sin bins, metres and m/s."""
    p = frame.profile
    lp = frame.log_power()
    ra, rd = transforms.ra_view(lp, is_log_power=True), transforms.rd_view(lp, is_log_power=True)
    ra_extent = (-1.0, 1.0, 0.0, p.max_range)  # sin(theta) across, range up
    rd_extent = (float(p.velocity_mps(0)), float(p.velocity_mps(p.n_doppler)), 0.0, p.max_range)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), gridspec_kw={"width_ratios": [1.3, 1]})
    im = axes[0].imshow(ra, origin="lower", aspect="auto", extent=ra_extent, cmap="viridis")
    axes[1].imshow(rd, origin="lower", aspect="auto", extent=rd_extent, cmap="viridis")
    fig.colorbar(im, ax=axes[0], label="dB")
    if frame.labels is not None:
        _overlay(axes[0], frame.ra_mask(), ra_extent, p.num_classes)
        _overlay(axes[1], frame.rd_mask(), rd_extent, p.num_classes)
    for o in frame.objects:
        if o.n_voxels == 0:
            continue
        rng = float(np.hypot(o.centre_x, o.centre_y))
        axes[0].annotate(o.class_name, (o.centre_x / max(rng, 1e-6), rng), color="white", fontsize=8,
                         xytext=(4, 4), textcoords="offset points")
        axes[1].annotate(o.class_name, (float(p.velocity_mps(o.doppler_bin)), rng), color="white", fontsize=8,
                         xytext=(4, 4), textcoords="offset points")
    axes[0].set(xlabel="sin(azimuth)  (right > 0)", ylabel="range (m)", title="RA: max log power over Doppler")
    axes[1].set(xlabel="radial velocity (m/s, receding > 0)", ylabel="range (m)",
                title="RD: log power summed over angle")
    handles = [plt.Rectangle((0, 0), 1, 1, color=CLASS_COLOURS[c][:7]) for c in range(1, p.num_classes)]
    fig.legend(handles, p.class_names, loc="lower center", ncol=p.num_classes - 1, frameon=False)
    fig.suptitle(title or f"{p.name}  {frame.sequence} frame {frame.index}")
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
