"""The simulator's version moves with what a fixed seed produces (radar/simulate/version.py).

If this test fails after a change to the simulator, that change altered the data every seed makes:
bump ``SIMULATOR_VERSION``, say what changed in ``SIMULATOR_HISTORY`` and in the README's simulator
section, and record the new fingerprint below under the new version (the old ones stay: they document
what each version made).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from radar.simulate import SIMULATOR_HISTORY, SIMULATOR_VERSION, SimulatorConfig, simulate_sequence
from radar.transforms import log_power

SEED = 2026  # frame 0 of sequence 0: two pedestrians, a cyclist and a car on the small preset

# Per version: sha256 of the frame's labels and instances (exact), and its log power averaged over
# 4 x 4 x 2 blocks of (32, 32, 16) voxels, in dB: averages of 16 k voxels are stable to ~1e-5 dB across
# machines, while any change of the scene, noise or processing moves some block by >= 0.01 dB
# (TDM coupling on or off: by up to 0.5 dB).
FINGERPRINTS = {
    2: {
        "labels_sha256": "4a99d4f1d41388d8",
        "block_log_power_db": [
            55.783, 55.551, 56.618, 56.521, 56.265, 57.051, 55.955, 56.507, 57.419, 56.431, 56.743, 56.391,
            55.38, 56.668, 55.886, 55.956, 56.03, 55.979, 55.768, 56.038, 55.47, 56.49, 56.14, 57.467,
            55.372, 56.014, 55.689, 57.042, 55.462, 56.307, 55.688, 55.714,
        ],
    },
}
FINGERPRINTS[3] = FINGERPRINTS[2]  # version 3 changed indoor scenes only: the small preset's frame is version 2's
TOLERANCE_DB = 0.005


def fingerprint(config: SimulatorConfig | None = None) -> dict:
    frame = next(simulate_sequence("small", 1, seed=SEED, config=config))
    power = log_power(frame.cube).astype(np.float64)
    R, A, D = power.shape
    blocks = power.reshape(4, R // 4, 4, A // 4, 2, D // 2).mean(axis=(1, 3, 5))
    return {"labels_sha256": hashlib.sha256(frame.labels.tobytes() + frame.instances.tobytes()).hexdigest()[:16],
            "block_log_power_db": blocks.ravel()}


def test_a_fixed_seed_makes_what_its_version_says():
    assert SIMULATOR_VERSION in FINGERPRINTS, (
        f"SIMULATOR_VERSION {SIMULATOR_VERSION} has no recorded fingerprint: add fingerprint()'s output for it")
    expected, found = FINGERPRINTS[SIMULATOR_VERSION], fingerprint()
    assert found["labels_sha256"] == expected["labels_sha256"], (
        "the simulator's labels for a fixed seed changed without a SIMULATOR_VERSION bump")
    drift = np.abs(found["block_log_power_db"] - np.asarray(expected["block_log_power_db"])).max()
    assert drift <= TOLERANCE_DB, (
        f"the simulator's cubes for a fixed seed changed by up to {drift:.3f} dB without a SIMULATOR_VERSION bump")


def test_the_fingerprint_sees_the_last_change():
    # version 2 turned TDM coupling on: the fingerprint must tell its cubes from version 1's (the labels,
    # drawn from uncoupled kernels once compensated, are the same)
    before = fingerprint(SimulatorConfig(tdm_coupling=False))
    drift = np.abs(before["block_log_power_db"] - np.asarray(FINGERPRINTS[2]["block_log_power_db"])).max()
    assert drift > 20 * TOLERANCE_DB


def test_every_version_is_explained_and_the_docs_state_the_current_one():
    assert sorted(SIMULATOR_HISTORY) == list(range(1, SIMULATOR_VERSION + 1))
    page = (Path(__file__).resolve().parents[2] / "docs" / "reference" / "data.md").read_text()
    assert f"simulator version {SIMULATOR_VERSION}" in page.lower()


def test_a_frame_carries_the_simulators_version_and_options():
    config = SimulatorConfig(clutter=False)
    frame = next(simulate_sequence("small", 1, seed=SEED, config=config))
    assert frame.extras["simulator"] == {"version": SIMULATOR_VERSION, "options": config.to_dict()}
    assert frame.extras["simulator"]["options"]["clutter"] is False
