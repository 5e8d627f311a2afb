"""The detection step, one function for every caller: normalise the log power, run the detector, decode
its centres (top ``k`` above a score), refine their Doppler from the cube (docs/design.md sections 5-6).

:meth:`models.erasenet.model.EraseNet.segment` times normalisation and detection as two stages, so it calls the
two halves (:func:`normalise_log_power`, :func:`decode_centres`); evaluation, the trainer's validation AP
and the seed-jitter measurement call :func:`detect_centres`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from radar.centres import MAX_OBJECTS, Centres
from radar.doppler import DOPPLER_REFINEMENT, DopplerRefinement, refine_doppler


def normalise_log_power(log_power_db: torch.Tensor, mean_db: float, std_db: float, *,
                        out: torch.Tensor | None = None) -> torch.Tensor:
    """The detector's input: ``(log power - mean) * (1 / std)`` (any shape; (B, D, R, A) for the detector), written
    into ``out`` (``log_power_db`` itself normalises in place) or one new tensor: no temporary the input's size."""
    return torch.sub(log_power_db, mean_db, out=out).mul_(1.0 / std_db)


def decode_centres(detector: nn.Module, outputs: dict[str, torch.Tensor], log_power_rad: Sequence[np.ndarray], *,
                   k: int = MAX_OBJECTS, score_threshold: float,
                   doppler_refinement: DopplerRefinement | None = DOPPLER_REFINEMENT) -> list[Centres]:
    """Centres of each frame from the detector's ``outputs``: top ``k`` above ``score_threshold``, their
    Doppler refined from the frame's log power ``log_power_rad[b]`` (R, A, D) dB unless ``doppler_refinement``
    is None (the detector compresses D bins to 3 channels)."""
    frames = []
    for b, decoded in enumerate(detector.decode(outputs, k=k, score_threshold=score_threshold)):
        centres = Centres.from_mapping(decoded)
        if doppler_refinement is not None:
            centres = refine_doppler(log_power_rad[b], centres, doppler_refinement)
        frames.append(centres)
    return frames


def detect_centres(detector: nn.Module, log_power_dra: torch.Tensor, *, mean_db: float, std_db: float,
                   k: int = MAX_OBJECTS, score_threshold: float,
                   doppler_refinement: DopplerRefinement | None = DOPPLER_REFINEMENT,
                   device: torch.device | str = "cpu", history: torch.Tensor | None = None,
                   history_present: torch.Tensor | None = None) -> tuple[dict[str, torch.Tensor], list[Centres]]:
    """The whole step on a batch of log power (B, D, R, A) dB (the store's layout): the detector's outputs
    (for a loss) and each frame's centres. ``history`` (B, H, D, R, A) dB and ``history_present`` (B, H): the
    earlier frames of each frame's sequence, for a detector that reads them (absent frames are zeroed)."""
    x = normalise_log_power(log_power_dra, mean_db, std_db).to(device)
    if history is None:
        outputs = detector(x)
    else:
        present = history_present.to(device)
        earlier = normalise_log_power(history, mean_db, std_db).to(device) * present[:, :, None, None, None]
        outputs = detector(x, history=earlier, history_present=present)
    # (D, R, A) -> (R, A, D) views, for the Doppler refinement
    log_power_rad = [frame.float().cpu().numpy().transpose(1, 2, 0) for frame in log_power_dra]
    return outputs, decode_centres(detector, outputs, log_power_rad, k=k, score_threshold=score_threshold,
                                   doppler_refinement=doppler_refinement)
