"""``radarseg segment CUBE.npy``: ERASE-Net on one cube file, with a picture of the prediction."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from models.engines import load_erasenet
from radar import transforms
from radar.io.npy import load_npy


def segment_file(cube_path: str | Path, *, detector: str | Path, segmenter: str | Path, is_log_power: bool = False,
                 png: str | Path | None = None, score_threshold: float = 0.3, engine: str = "torch") -> dict[str, Any]:
    """Segment a .npy cube (complex or magnitude RAD, or log power) and return objects and compute.

    ``engine``: "torch" or "onnx" (``models.engines``)."""
    net = load_erasenet(detector, segmenter, engine=engine, score_threshold=score_threshold)
    dtypes = (np.floating,) if is_log_power else (np.complexfloating, np.floating)
    cube = load_npy(cube_path, shape=net.profile.shape, dtypes=dtypes, what="RAD cube")
    result = net.segment(cube, is_log_power=is_log_power)
    if png is not None:
        from pipelines.figures import plot_prediction

        log_power = cube.astype(np.float32) if is_log_power else transforms.log_power(cube)
        plot_prediction(log_power, net.profile, result.ra_mask, result.rd_mask, result.objects, png,
                        title=f"ERASE-Net on {Path(cube_path).name}")
    return {"objects": [o.to_dict() for o in result.objects], "compute": result.compute,
            "png": None if png is None else str(png)}
