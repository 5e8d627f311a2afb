"""A served model for the radar that recorded OpenRadar's frames (docs/profiles/openradar_ti_2tx4rx.toml): untrained
tiny networks (seed 0) saved as the trainers save a radar described by a file, and the recorded frame as the ADC
chain's layouts, a capture and undecoded words."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radar.adc import ti_to_sck
from radar.profiles import RadarProfile, describe_for_storage
from radar.profiles.files import load_profile_file

ROOT = Path(__file__).resolve().parents[2]
PROFILE_FILE = ROOT / "docs" / "profiles" / "openradar_ti_2tx4rx.toml"
FRAME_FILE = ROOT / "tests" / "fixtures" / "openradar" / "doppler_example_1.npy"


def openradar_profile() -> RadarProfile:
    return load_profile_file(PROFILE_FILE)


def save_openradar_checkpoints(root: Path) -> tuple[Path, Path]:
    """Tiny detector and segmenter for the OpenRadar radar, random weights of seed 0."""
    import torch

    from models.checkpoint import Checkpoint, save_checkpoint
    from models.registry import create_model

    profile = openradar_profile()
    torch.manual_seed(0)
    paths = []
    for key, name in (("detector", "centre_detector_tiny"), ("segmenter", "minkunet_tiny")):
        model = create_model(name, preset=profile)
        checkpoint = Checkpoint(model_name=name, config={"preset": profile.name}, state_dict=model.state_dict(),
                                preset=profile.name, class_names=("background", *profile.class_names),
                                extra={"stage": key, "radar_file": describe_for_storage(profile)})
        paths.append(save_checkpoint(checkpoint, Path(root) / f"openradar-{key}.pt"))
    return paths[0], paths[1]


def ti_frame_iq() -> np.ndarray:
    """doppler_example_1 in the "ti" layout (chirps, rx, samples) as int16 with I/Q on a trailing axis of 2
    (the fixture's loops x virtual antennas, TX-major, are the TX-interleaved chirps of a 2-TX radar)."""
    iq = np.load(FRAME_FILE)
    return iq.reshape(-1, 4, iq.shape[2], 2)


def as_complex(iq: np.ndarray) -> np.ndarray:
    return (iq[..., 0].astype(np.float32) + 1j * iq[..., 1].astype(np.float32)).astype(np.complex64)


def sck_frame() -> np.ndarray:
    """The same frame as complex64 in the "sck" layout (samples, chirps, virtual elements)."""
    return ti_to_sck(as_complex(ti_frame_iq()), openradar_profile())


def undecoded_words() -> np.ndarray:
    """The frame as OpenRadar published it: complex128 whose parts are the raw 16-bit words 0..65535 ("ti")."""
    words = ti_frame_iq().view(np.uint16).astype(np.float64)
    return words[..., 0] + 1j * words[..., 1]
