"""Simulated recordings on disk: ``radarseg simulate``."""

from __future__ import annotations

import logging
from pathlib import Path

from pipelines.progress import progress as progress_bar
from radar.errors import UserError
from radar.io.recording import RecordingWriter
from radar.profiles import get_profile
from radar.simulate import SimulatorConfig, simulate_sequence

log = logging.getLogger(__name__)


def simulate_recording(*, preset: str, sequences: int, frames: int, seed: int, out: str | Path,
                       config: SimulatorConfig | None = None, progress: bool = True, adc: bool = False) -> Path:
    """Simulate ``sequences`` x ``frames`` labelled frames into the recording layout at ``out``
    (``adc``: store the raw ADC samples instead of the RAD cubes)."""
    if sequences < 1 or frames < 1:
        raise UserError(f"sequences and frames must be >= 1, got {sequences} and {frames}")
    profile = get_profile(preset)
    config = config or SimulatorConfig()
    source = {"kind": "sim", "seed": seed, "simulator": config.stamp()}
    with RecordingWriter(out, profile, source=source, content="adc" if adc else "cube") as writer, \
            progress_bar(total=sequences * frames, desc=f"simulate {preset}", unit="frame",
                         disable=not progress) as bar:
        for s in range(sequences):
            for frame in simulate_sequence(profile, frames, seed=seed, sequence_index=s, config=config):
                writer.write(frame)
                bar.update(1)
    log.info("wrote %d frames to %s", sequences * frames, out)
    return Path(out)
