"""The scene simulator: sequences of labelled RAD frames from moving extended targets and clutter."""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from radar.adc import adc_to_rad
from radar.frame import ObjectRecord, RadarFrame
from radar.instances import instance_stats
from radar.profiles import RadarProfile, get_profile
from radar.simulate.channels import draw_channel_gains
from radar.simulate.fmcw import Scatterers, received_amplitude, synthesize_adc
from radar.simulate.indoor import IndoorSceneGenerator, indoor_clutter
from radar.simulate.labels import exact_labels
from radar.simulate.multipath import multipath_ghosts
from radar.simulate.scene import ObjectState, SceneGenerator, StaticClutter, static_clutter
from radar.simulate.targets import class_model, object_scatterers
from radar.simulate.version import SIMULATOR_VERSION


@dataclass(frozen=True)
class SimulatorConfig:
    """Simulator switches and label thresholds (dB)."""

    label_snr_db: float = 6.0  # a labelled voxel is at least this far above the noise floor
    label_peak_db: float = 20.0  # ... and within this of its object's own peak
    # TDM Doppler-angle coupling in the ADC samples, as a real TDM-MIMO radar records them (a TX firing
    # later in the chirp cycle sees the target moved further), removed by the processing chain: the ADC
    # then processes into the frame's cube by radar.adc.process_adc's defaults on every path.
    tdm_coupling: bool = True
    tdm_compensation: bool = True  # ... removed by the processing chain (only applies with coupling)
    clutter: bool = True
    multipath: bool = True  # ghosts of the objects off the scene's walls (indoor scenes; road scenes have no mirrors)
    noise: bool = True
    rcs_fluctuation_db: float = 2.0  # per-scatterer RCS std from frame to frame

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def stamp(self) -> dict[str, Any]:
        """What a store or recording records of the simulator that made it: ``{"version", "options"}``."""
        return {"version": SIMULATOR_VERSION, "options": self.to_dict()}


def sequence_name(sequence_index: int) -> str:
    return f"seq_{sequence_index:03d}"


@contextmanager
def _timed(timings: dict[str, float] | None, key: str):
    start = time.perf_counter()
    yield
    if timings is not None:
        timings[key] = timings.get(key, 0.0) + time.perf_counter() - start


def _object_scatterers(profile: RadarProfile, state: ObjectState, t: float, rng: np.random.Generator,
                       config: SimulatorConfig) -> tuple[Scatterers, float]:
    """World-frame scatterers of one object, and its total RCS this frame (dBsm)."""
    rcs_total = state.rcs_dbsm + rng.normal(0.0, config.rcs_fluctuation_db / 2)
    x, y, vx, vy, rcs = object_scatterers(
        class_model(state.class_name), x=state.x, y=state.y, heading=state.heading, speed=state.speed,
        rcs_dbsm=rcs_total, t=t, gait_phase=state.gait_phase, rng=rng,
        fluctuation_db=config.rcs_fluctuation_db,
    )
    # Each scatterer's carrier phase 4 pi R / lambda changes completely between frames: random phase.
    phase = np.exp(2j * np.pi * rng.random(len(x)))
    amplitude = received_amplitude(profile, np.hypot(x, y), rcs) * phase
    return Scatterers(x, y, vx, vy, amplitude), float(rcs_total)


def _clutter_scatterers(profile: RadarProfile, clutter: StaticClutter, rng: np.random.Generator) -> Scatterers:
    zeros = np.zeros(len(clutter.x))
    phase = np.exp(2j * np.pi * rng.random(len(clutter.x)))
    amplitude = received_amplitude(profile, np.hypot(clutter.x, clutter.y), clutter.rcs_dbsm) * phase
    return Scatterers(clutter.x, clutter.y, zeros, zeros, amplitude)


def simulate_frame(profile: RadarProfile, states: list[ObjectState], clutter: StaticClutter | None, *,
                   t: float, rng: np.random.Generator, config: SimulatorConfig, sequence: str = "seq_000",
                   index: int = 0, timings: dict[str, float] | None = None,
                   channel_gains: np.ndarray | None = None) -> RadarFrame:
    """One labelled frame of the given object states at scene time ``t`` (s).

    ``timings`` (optional) accumulates seconds spent in ``synthesis``, ``fft`` and ``labels``.
    The frame's ``extras["simulator"]`` is the simulator's version and options
    (:meth:`SimulatorConfig.stamp`); ``extras["object_scatterers"]`` holds each object's scatterers (instance i+1 = list
    index i) so a response can be recomputed independently; ``extras["adc"]`` the raw ADC samples
    (Ns, Nc, K) the cube was processed from. ``channel_gains`` (K,): the radar's channel errors
    (radar/simulate/channels.py), in the samples and in the labels alike.
    """
    with _timed(timings, "synthesis"):
        per_object, rcs_totals = [], []
        for state in states:
            scat, rcs_total = _object_scatterers(profile, state, t, rng, config)
            per_object.append(scat)
            rcs_totals.append(rcs_total)
        parts = list(per_object)
        if config.clutter and clutter is not None:
            parts.append(_clutter_scatterers(profile, clutter, rng))
            if config.multipath and len(clutter.mirrors):
                parts.append(multipath_ghosts(profile, per_object, clutter.mirrors, rng))
        adc = synthesize_adc(profile, Scatterers.concat(parts), tdm_coupling=config.tdm_coupling,
                             noise_rng=rng if config.noise else None, channel_gains=channel_gains)
    compensated = config.tdm_coupling and config.tdm_compensation
    with _timed(timings, "fft"):
        cube = adc_to_rad(profile, adc, tdm_compensation=compensated)
    with _timed(timings, "labels"):
        labels, instances = exact_labels(
            profile, per_object, [s.class_id for s in states], snr_db=config.label_snr_db,
            # Compensation evaluated at each scatterer's own Doppler undoes its coupling exactly at its
            # Doppler peak (and to within a bin's phase elsewhere): labels then use uncoupled kernels.
            peak_db=config.label_peak_db, tdm_coupling=config.tdm_coupling and not compensated,
            channel_gains=channel_gains,
        )
        stats = instance_stats(instances, profile, n_instances=len(states))
        objects = tuple(
            ObjectRecord(
                instance_id=i + 1, class_id=s.class_id, class_name=s.class_name,
                n_voxels=int(stats.n_voxels[i + 1]), centre_x=float(stats.x[i + 1]),
                centre_y=float(stats.y[i + 1]), centre_range_bin=float(stats.range_bin[i + 1]),
                centre_angle_bin=float(stats.angle_bin[i + 1]), doppler_bin=float(stats.doppler_bin[i + 1]),
                true_range_m=s.range_m, true_angle_deg=s.angle_deg, true_velocity_mps=s.radial_velocity,
                rcs_dbsm=rcs_totals[i], track_id=s.track_id, true_vx=s.vx, true_vy=s.vy,
            )
            for i, s in enumerate(states)
        )
    return RadarFrame(cube=cube, profile=profile, sequence=sequence, index=index, labels=labels,
                      instances=instances, objects=objects,
                      extras={"object_scatterers": per_object, "adc": adc, "tdm_coupling": config.tdm_coupling,
                              "tdm_compensation": compensated,
                              "simulator": config.stamp()})


def simulate_sequence(preset: str | RadarProfile, n_frames: int, *, seed: int, sequence_index: int = 0,
                      config: SimulatorConfig | None = None, timings: dict[str, float] | None = None,
                      only: Iterable[int] | None = None) -> Iterator[RadarFrame]:
    """Frames of one simulated sequence, reproducible from ``(seed, sequence_index)``.

    Objects move along smooth trajectories at the profile's frame rate; the static clutter of the
    scene stays put. Frames are generated lazily (one cube in memory at a time). ``only`` (ascending
    frame indices) yields just those frames, identical to the full run's: the scene is stepped
    through the others (cheap) and no cube is synthesised for them (for shard-parallel jobs). A profile with a
    ``[scene]`` table gets indoor scenes (radar/simulate/indoor.py) instead of road scenes.
    """
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    wanted = range(n_frames) if only is None else list(only)
    if any(b <= a for a, b in zip(wanted, wanted[1:], strict=False)) or any(not 0 <= i < n_frames for i in wanted):
        raise ValueError(f"only must list ascending frame indices in [0, {n_frames}), got {list(wanted)}")
    profile = get_profile(preset)
    config = config or SimulatorConfig()
    scene_rng = np.random.default_rng([seed, sequence_index, 0])
    settings = profile.extra.get("scene")  # a [scene] table: rooms at the radar's scale; else road scenes
    if settings is None:
        scene = SceneGenerator(profile, scene_rng)
        clutter = static_clutter(profile, scene_rng)
    else:
        scene = IndoorSceneGenerator(profile, settings, scene_rng)
        clutter = indoor_clutter(profile, settings, scene_rng)
    gains = draw_channel_gains(profile, scene_rng)  # this sequence's radar: None (nothing drawn) for ideal channels
    name = sequence_name(sequence_index)
    index = 0
    for target in wanted:
        while index < target:  # step the scene through the frames nobody asked for
            scene.step()
            index += 1
        states = scene.step()
        index += 1
        frame_rng = np.random.default_rng([seed, sequence_index, 1, target])
        yield simulate_frame(profile, states, clutter, t=target * profile.frame_period_s, rng=frame_rng,
                             config=config, sequence=name, index=target, timings=timings, channel_gains=gains)
