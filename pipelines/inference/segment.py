"""``radarseg segment CUBE.npy``: ERASE-Net on one cube file, with a picture of the prediction."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from models.checkpoint import load_pair
from models.runtime import load_erasenet
from radar.centres import SCORE_THRESHOLD
from radar.errors import DataError
from radar.input_kind import InputKind, check_values, parse_kind, resolve_kind
from radar.io.npy import load_npy


def segment_file(cube_path: str | Path, *, detector: str | Path, segmenter: str | Path,
                 input_kind: InputKind | str | None = None, png: str | Path | None = None,
                 score_threshold: float = SCORE_THRESHOLD, runtime: str = "torch",
                 warm_up: bool = True) -> dict[str, Any]:
    """Segment a .npy cube and return objects and compute. ``input_kind`` says what the cube holds
    (radar.input_kind: complex, magnitude, log_power, adc); a complex cube needs none, a real-valued one must
    say it. Values impossible for the kind are refused (InputKindError, a ValueError) naming the likely mistake.
    ``runtime``: what runs the pair (``models.runtime.RUNTIMES``; the int8 ones calibrate on simulated frames of
    the preset). With ``warm_up`` the cube is segmented once
    before the run whose compute is reported, so its seconds are a steady frame's, not the process's first
    (which pays one-off costs: the first call of every kernel, allocator growth)."""
    declared = parse_kind(input_kind) if isinstance(input_kind, str) else input_kind
    det, seg = load_pair(detector, segmenter)  # checked before anything is built or read
    profile = det.profile
    if declared is InputKind.adc:
        from radar.adc import adc_shape

        shape, what = adc_shape(profile), "ADC samples (samples, chirps, virtual elements)"
    else:
        shape, what = profile.shape, "RAD cube (range, angle, Doppler)"
    try:
        cube = load_npy(cube_path, shape=shape, dtypes=(np.complexfloating, np.floating), what=what)
    except DataError as exc:
        if "has shape" not in str(exc):
            raise
        # a cube of another radar: say whose cubes these checkpoints read, and where a model for it comes from
        hint = (f"these checkpoints were trained for the radar {profile.name!r}; a cube of another radar needs a "
                f"model trained for its profile: docs/guides/own-radar.md")
        raise DataError(None, f"{exc} ({hint})") from None
    try:
        kind = resolve_kind(cube.dtype, declared)
        check_values(cube, kind)
    except ValueError as exc:
        raise DataError(cube_path, str(exc)) from None
    net = load_erasenet(det, seg, runtime, score_threshold=score_threshold)
    rad_kind = kind  # what the RAD cube the model reads holds
    if kind is InputKind.adc:
        from radar.adc import process_adc

        cube, rad_kind = process_adc(cube, net.profile), InputKind.complex
    if warm_up:
        net.segment(cube, kind=rad_kind)
    result = net.segment(cube, kind=rad_kind, keep_log_power=png is not None)
    if png is not None:
        from pipelines.figures import plot_prediction

        plot_prediction(result.log_power, net.profile, result.ra_mask, result.rd_mask, result.objects, png,
                        title=f"ERASE-Net on {Path(cube_path).name}")
    return {"objects": [o.to_dict() for o in result.objects], "compute": result.compute.to_dict(),
            "png": None if png is None else str(png), "input": kind.value, "timed_after_warm_up": warm_up,
            "runtime": str(runtime)}
