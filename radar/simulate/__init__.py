"""FMCW scene simulator with exact labels (the embedded default data source)."""

from radar.simulate.fmcw import point_target_cube
from radar.simulate.simulator import SimulatorConfig, sequence_name, simulate_frame, simulate_sequence
from radar.simulate.version import SIMULATOR_HISTORY, SIMULATOR_VERSION

__all__ = ["SIMULATOR_HISTORY", "SIMULATOR_VERSION", "SimulatorConfig", "point_target_cube", "sequence_name",
           "simulate_frame", "simulate_sequence"]
