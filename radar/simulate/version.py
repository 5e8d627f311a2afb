"""The simulator's version: what a given seed produces.

Every change to what ``simulate_sequence(preset, n, seed=s)`` yields for some seed (cubes, labels or
object tables, with default options) bumps :data:`SIMULATOR_VERSION` and adds a line to
:data:`SIMULATOR_HISTORY`; ``tests/radar/test_simulator_version.py`` fails when a fixed seed's output
changes while the version stays. Stores and recordings made from the simulator record
``SimulatorConfig.stamp()`` (the version and the options), so results computed on them say which
simulator made their data.
"""

SIMULATOR_VERSION = 3

SIMULATOR_HISTORY = {
    1: "the first simulator (up to commit 7ca8875): ADC synthesised without TDM Doppler-angle coupling",
    2: "TDM Doppler-angle coupling on by default (a TX firing later in the chirp cycle sees the target moved "
       "further), compensated per Doppler bin by the processing chain (commit 811ae5d)",
    3: "indoor scenes (a profile with a [scene] table) get multipath ghosts of the walkers off the room's walls "
       "and a TX-RX coupling level drawn per room; a profile may state its channels' phase and gain errors "
       "([simulation] channel_phase_error_deg, channel_gain_error_db), drawn per sequence; road scenes (every "
       "built-in preset) are unchanged",
}

