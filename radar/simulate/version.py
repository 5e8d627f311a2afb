"""The simulator's version: what a given seed produces.

Every change to what ``simulate_sequence(preset, n, seed=s)`` yields for some seed (cubes, labels or
object tables, with default options) bumps :data:`SIMULATOR_VERSION` and adds a line to
:data:`SIMULATOR_HISTORY`; ``tests/radar/test_simulator_version.py`` fails when a fixed seed's output
changes while the version stays. Stores and recordings made from the simulator record
``SimulatorConfig.stamp()`` (the version and the options), so results computed on them say which
simulator made their data.
"""

SIMULATOR_VERSION = 2

SIMULATOR_HISTORY = {
    1: "the first simulator (up to commit 7ca8875): ADC synthesised without TDM Doppler-angle coupling",
    2: "TDM Doppler-angle coupling on by default (a TX firing later in the chirp cycle sees the target moved "
       "further), compensated per Doppler bin by the processing chain (commit 811ae5d)",
}

