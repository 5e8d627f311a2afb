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
from radar.input_kind import InputKind
from radar.profiles import RadarProfile  # noqa: E402

CLASS_COLOURS = ["#00000000", "#ff4040", "#40c0ff", "#ffd000", "#60ff60"]


def _overlay(ax, mask: np.ndarray, extent, num_classes: int) -> None:
    cmap = ListedColormap(CLASS_COLOURS[:num_classes])
    ax.imshow(np.ma.masked_equal(mask, 0), origin="lower", aspect="auto", extent=extent, cmap=cmap,
              vmin=0, vmax=num_classes - 1, alpha=0.45, interpolation="nearest")
    for c in range(1, num_classes):
        if (mask == c).any():
            ax.contour((mask == c).astype(float), levels=[0.5], colors=[CLASS_COLOURS[c][:7]], linewidths=0.8,
                       origin="lower", extent=extent)


def draw_views(axes, log_power: np.ndarray, profile: RadarProfile, ra_mask: np.ndarray | None,
               rd_mask: np.ndarray | None, annotations: list[tuple[str, float, float, float]], *,
               colorbar: bool = True, empty_note: str | None = None) -> None:
    """RA view (azimuth x range: uniform in sin(azimuth), ticks in degrees) on ``axes[0]`` and RD view (velocity x
    range) on ``axes[1]``, masks drawn over them and ``annotations`` ``(text, x m, y m, radial velocity m/s)``
    placed on both; a colour bar (dB) beside each view (``colorbar``); ``empty_note`` (e.g. "no detections")
    written on both views when there is no annotation and no masked pixel, so an empty prediction does not look
    like a bug."""
    p = profile
    db = InputKind.log_power
    ra, rd = transforms.ra_view(log_power, kind=db), transforms.rd_view(log_power, kind=db)
    ra_extent = (-1.0, 1.0, 0.0, p.max_range)
    rd_extent = (float(p.velocity_mps(0)), float(p.velocity_mps(p.n_doppler)), 0.0, p.max_range)
    images = (axes[0].imshow(ra, origin="lower", aspect="auto", extent=ra_extent, cmap="viridis"),
              axes[1].imshow(rd, origin="lower", aspect="auto", extent=rd_extent, cmap="viridis"))
    if colorbar:  # the two views have their own dB scales (max over Doppler; log of the sum over angle)
        for ax, image in zip(axes, images, strict=True):
            ax.figure.colorbar(image, ax=ax, label="dB", fraction=0.06, pad=0.02)
    empty = not annotations and not any(m is not None and m.any() for m in (ra_mask, rd_mask))
    if empty_note and empty:
        for ax in axes:
            ax.text(0.5, 0.5, empty_note, transform=ax.transAxes, ha="center", va="center", color="white",
                    fontsize=11, bbox={"facecolor": "black", "alpha": 0.6, "edgecolor": "none"})
    if ra_mask is not None:
        _overlay(axes[0], ra_mask, ra_extent, p.num_classes)
    if rd_mask is not None:
        _overlay(axes[1], rd_mask, rd_extent, p.num_classes)
    for n, (text, x, y, velocity) in enumerate(annotations):
        rng = float(np.hypot(x, y))
        # labels point away from the middle, so two objects on either side of it keep their labels on their own
        # side, but inwards within the outer fifth of a view (never cut at its edge); they alternate up and down
        for ax, at, (lo, hi) in ((axes[0], x / max(rng, 1e-6), ra_extent[:2]), (axes[1], velocity, rd_extent[:2])):
            edge = 0.2 * (hi - lo)
            right = at > hi - edge or (lo + edge <= at < (lo + hi) / 2)  # text ends at the point (to its left)
            ax.annotate(text, (at, rng), color="white", fontsize=8, xytext=(-4 if right else 4, 4 if n % 2 else -10),
                        textcoords="offset points", ha="right" if right else "left", annotation_clip=True)
    # The RA image is uniform in sin(azimuth) (the angle FFT's bins); its axis is labelled in degrees, like the
    # viewer's and the API's.
    degrees = np.array([-60, -30, 0, 30, 60])
    axes[0].set_xticks(np.sin(np.radians(degrees)), [f"{d:d}" for d in degrees])
    axes[0].set(xlabel="azimuth (deg, right > 0)", ylabel="range (m)", title="RA: max log power over Doppler")
    axes[1].set(xlabel="radial velocity (m/s, receding > 0)", ylabel="range (m)",
                title="RD: log power summed over angle")


def _finish(fig, profile: RadarProfile, title: str, path: str | Path) -> Path:
    handles = [plt.Rectangle((0, 0), 1, 1, color=CLASS_COLOURS[c][:7]) for c in range(1, profile.num_classes)]
    fig.legend(handles, profile.class_names, loc="lower center", ncol=profile.num_classes - 1, frameon=False)
    fig.suptitle(title)
    height = fig.get_figheight()  # keep about 0.3 inch for the title and the legend, whatever the figure's size
    fig.tight_layout(rect=(0, min(0.05, 0.45 / height), 1, 1 - 0.3 / height))
    return save_figure(fig, path)


def save_figure(fig, path: str | Path) -> Path:  # noqa: ANN001 (a matplotlib Figure)
    """Write ``fig`` as a PNG at ``path`` (folders made as needed), close it, return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_frame_views(frame: RadarFrame, path: str | Path, *, title: str | None = None) -> Path:
    """Write a PNG with the RA and RD views of ``frame``, its label masks and object names drawn over them."""
    p = frame.profile
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), gridspec_kw={"width_ratios": [1.3, 1]})
    has_labels = frame.labels is not None
    annotations = [(o.class_name, o.centre_x, o.centre_y, float(p.velocity_mps(o.doppler_bin)))
                   for o in frame.objects if o.n_voxels > 0]
    draw_views(axes, frame.log_power(), p, frame.ra_mask() if has_labels else None,
               frame.rd_mask() if has_labels else None, annotations)
    return _finish(fig, p, title or f"{p.name}  {frame.sequence} frame {frame.index}", path)


def plot_prediction(log_power: np.ndarray, profile: RadarProfile, ra_mask: np.ndarray, rd_mask: np.ndarray,
                    objects: list, path: str | Path, *, title: str = "prediction") -> Path:
    """Write a PNG with the RA and RD views of a cube and a prediction's masks and objects drawn over them
    (``objects`` carry ``class_name, score, x, y, velocity_mps``, as :class:`models.erasenet.model.SegmentedObject`)."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2), gridspec_kw={"width_ratios": [1.3, 1]})
    annotations = [(f"{o.class_name} {o.score:.2f}", o.x, o.y, o.velocity_mps) for o in objects]
    draw_views(axes, log_power, profile, ra_mask, rd_mask, annotations, empty_note="no detections")
    return _finish(fig, profile, title, path)


def plot_truth_vs_prediction(log_power: np.ndarray, profile: RadarProfile, truth: tuple[np.ndarray, np.ndarray],
                             prediction: tuple[np.ndarray, np.ndarray], path: str | Path, *,
                             truth_objects: list[tuple[str, float, float, float]] | None = None,
                             predicted_objects: list[tuple[str, float, float, float]] | None = None,
                             title: str = "ground truth (top) / prediction (bottom)") -> Path:
    """Write a PNG of one frame: RA and RD views with the ground-truth masks ``truth`` ((R, A), (R, D))
    on the top row and the predicted masks ``prediction`` on the bottom row; optional annotations
    ``(text, x m, y m, radial velocity m/s)`` per row."""
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.6), gridspec_kw={"width_ratios": [1.3, 1]})
    for row, (masks, notes, label, empty) in enumerate(((truth, truth_objects, "truth", "no labelled objects"),
                                                        (prediction, predicted_objects, "prediction",
                                                         "no detections"))):
        draw_views(axes[row], log_power, profile, masks[0], masks[1], notes or [], empty_note=empty)
        for ax in axes[row]:
            ax.set_title(f"{label}: {ax.get_title()}", fontsize=9)
    return _finish(fig, profile, title, path)


def plot_compare_frames(frames: list[tuple[str, np.ndarray, dict[str, tuple[np.ndarray, np.ndarray]]]],
                        profile: RadarProfile, path: str | Path, *,
                        title: str = "the same frames, every model") -> Path:
    """Write a PNG with one row per model and an RA and an RD column per frame.

    ``frames``: ``(label, log_power (R, A, D) dB, {row name: (RA mask (R, A), RD mask (R, D))})``, every frame
    with the same row names in the same order (ground truth first, then the models).
    """
    names = list(frames[0][2])
    fig, axes = plt.subplots(len(names), 2 * len(frames), figsize=(3.2 * 2 * len(frames), 2.7 * len(names) + 0.6),
                             gridspec_kw={"width_ratios": [1.3, 1] * len(frames)}, squeeze=False)
    for column, (label, log_power, masks) in enumerate(frames):
        for row, name in enumerate(names):
            pair = axes[row, 2 * column:2 * column + 2]
            draw_views(pair, log_power, profile, *masks[name], [], colorbar=False)
            for ax, view in zip(pair, ("RA", "RD"), strict=True):
                ax.set_title(f"{name}: {label} {view}", fontsize=8)
                ax.tick_params(labelsize=6)
                ax.xaxis.label.set_size(6)
                ax.yaxis.label.set_size(6)
    return _finish(fig, profile, title, path)


def plot_pr_curves(curves: dict[str, tuple[np.ndarray, np.ndarray, float]], path: str | Path, *,
                   title: str = "detection precision-recall") -> Path:
    """Write a PNG of precision-recall curves; ``curves[label] = (recall (N,), precision (N,), AP)``."""
    fig, ax = plt.subplots(figsize=(5.5, 5.2))
    for label, (recall, precision, ap) in curves.items():
        ax.plot(np.concatenate([[0.0], recall]), np.concatenate([[1.0], precision]), label=f"{label} (AP {ap:.3f})")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.01), ylim=(0, 1.02), title=title)
    ax.grid(alpha=0.3)
    # below the axes, so that no curve is hidden behind it (curves end low on the left)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8, frameon=False)
    fig.tight_layout()
    return save_figure(fig, path)


def plot_confusion(confusion: np.ndarray, class_names: tuple[str, ...] | list[str], path: str | Path, *,
                   title: str = "confusion matrix") -> Path:
    """Write a PNG of a (C, C) confusion matrix (rows truth, columns prediction), normalised per row,
    with the raw counts printed in the cells."""
    confusion = np.asarray(confusion, np.float64)
    rows = confusion / np.maximum(confusion.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    im = ax.imshow(rows, cmap="Blues", vmin=0, vmax=1)
    fig.colorbar(im, ax=ax, label="fraction of the true class")
    for i in range(len(rows)):
        for j in range(len(rows)):
            ax.text(j, i, f"{rows[i, j]:.2f}\n{int(confusion[i, j])}", ha="center", va="center", fontsize=7,
                    color="white" if rows[i, j] > 0.5 else "black")
    ax.set(xticks=range(len(rows)), yticks=range(len(rows)), xlabel="predicted", ylabel="true", title=title)
    ax.set_xticklabels(class_names, rotation=30)
    ax.set_yticklabels(class_names)
    fig.tight_layout()
    return save_figure(fig, path)
