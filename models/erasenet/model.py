"""End-to-end ERASE-Net inference with its compute report (docs/design.md sections 5-8, 10).

cube -> log transform -> normalised detector input -> detector -> decode -> region growing ->
ROI points -> sparse segmenter (its fused inference form, models.segmenter.fused) -> RAD label cube
(background outside the ROI) -> RA / RD masks -> objects. Every stage is timed; MACs are exact: the detector's
from the analytic counter (cached per input shape), the segmenter's from the pairs its sparse convs actually
processed.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from models.checkpoint import Checkpoint, load_pair
from models.compute import ComputeCounter, MacRecorder, count_params, counted_layers
from models.detector.inference import FrozenDetector
from models.erasenet.compute_report import STEPS, FrameCompute
from models.erasenet.detection import decode_centres, normalise_log_power
from models.segmenter.fused import FusedMinkUNet, fusable
from radar import transforms
from radar.centres import MAX_OBJECTS, SCORE_THRESHOLD, Centres
from radar.doppler import DOPPLER_REFINEMENT, DopplerRefinement
from radar.errors import UserError
from radar.input_kind import SCHEMA_CONTENT, InputKind, resolve_kind
from radar.profiles import RadarProfile, get_profile
from radar.region_growing import RegionGrowingConfig, Regions, grow_regions
from radar.roi import roi_points
from radar.schema import check_schema, cube_schema
from radar.track_priors import TrackPriors, centres_with_priors

OBJECT_CENTRES = ("seed", "voxels")
"""Where an object is placed (``EraseNet(object_centre=)``): its seed's centre and Doppler, or its voxels' mean."""


@dataclass(frozen=True)
class SegmentedObject:
    """One object found in a frame: the majority class of its segmented voxels, placed at its seed's centre and
    Doppler (or at its voxels' mean: ``EraseNet(object_centre="voxels")``)."""

    class_id: int
    class_name: str
    score: float  # detector score of the seed it grew from
    range_m: float
    angle_deg: float
    velocity_mps: float  # radial, positive receding
    x: float
    y: float
    n_voxels: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class SegmentationResult:
    """Prediction for one frame. ``labels`` (R, A, D) uint8; masks (R, A) and (R, D) uint8."""

    labels: np.ndarray
    ra_mask: np.ndarray
    rd_mask: np.ndarray
    objects: list[SegmentedObject]
    centres: Centres
    regions: Regions
    compute: FrameCompute
    # with segment(views=True): the RA (R, A) and RD (R, D) views of the input in dB (radar.transforms), from the
    # log power the model computed (timed with the projections)
    views: tuple[np.ndarray, np.ndarray] | None = None
    # with segment(keep_log_power=True): the frame's log power (R, A, D) dB, float32, as the model computed it (what
    # the next frame of a stream reads as its history)
    log_power: np.ndarray | None = None
    # with segment(priors=...): the centres that the tracks' predictions added (radar.track_priors)
    prior_seeds: int = 0


@contextmanager
def _stage(seconds: dict[str, float], name: str):
    start = time.perf_counter()
    yield
    seconds[name] = seconds.get(name, 0.0) + time.perf_counter() - start


class EraseNet:
    """The two-stage segmenter. Thread-safe for concurrent ``segment`` calls only if the caller
    serialises them (the segmenter's per-layer MAC counters are per call)."""

    runtime = "torch"
    """What runs the networks (:data:`models.runtime.RUNTIMES`), reported in the compute report: "torch-int8" once
    :func:`models.quantized.erasenet.to_int8` ran; ``models.export.onnx_engine``'s "onnx" or "onnx-int8"."""

    normalises_detector_input = True
    """The detector's input is normalised here (an exported graph that normalises its own input: False)."""

    precision = "float"
    """What the segmenter computes in: its form's ``precision`` (:meth:`use_segmenter_form`; int8:
    ``models.quantized``)."""

    def __init__(self, detector: nn.Module | None, segmenter: nn.Module, profile: RadarProfile | str, *,
                 class_names: tuple[str, ...] | None = None, mean_db: float = 0.0, std_db: float = 1.0,
                 score_threshold: float = SCORE_THRESHOLD, max_objects: int = MAX_OBJECTS,
                 doppler_refinement: DopplerRefinement | None = DOPPLER_REFINEMENT,
                 region_config: RegionGrowingConfig | None = None, device: str | torch.device = "cpu",
                 frozen_detector: bool = True, fused_segmenter: bool = True, object_centre: str = "seed"):
        """``frozen_detector``: run a detector that has a ``decode`` through
        :class:`models.detector.inference.FrozenDetector` (traced for this preset's input, BatchNorms folded,
        channels_last; a copy of its weights taken now). ``self.detector`` stays the eager module (its
        parameters and MACs are the ones reported). ``fused_segmenter``: run a MinkUNet segmenter through
        :class:`models.segmenter.fused.FusedMinkUNet` (BatchNorms folded, ReLU and residual sums in the kernels'
        output loop, MACs from the kernel maps; a copy of its weights taken now); other segmenters run eager.
        ``object_centre``: where an object is (its position and radial velocity): ``seed``, the centre and Doppler
        its seed was decoded at (the detector's sub-cell centre, Doppler refined from the cube), or ``voxels``, the
        mean position and circular-mean Doppler of its segmented voxels. ``seed`` by default: it places objects
        closer to the truth and its radial velocity has no heavy tail, which tracking needs (docs/guides/tracking.md
        and experiments/reports/tracking.md measure both).
        ``detector`` None: the centres always come from the caller (``segment(..., centres=...)``, e.g. CFAR); the
        detector then counts 0 parameters."""
        self.profile = get_profile(profile)
        self.class_names = tuple(class_names or self.profile.all_class_names)
        if len(self.class_names) != self.profile.num_classes:
            raise ValueError(f"{len(self.class_names)} class names for a {self.profile.num_classes}-class preset")
        if std_db <= 0:
            raise ValueError(f"std_db must be > 0, got {std_db}")
        self.device = torch.device(device)
        self.detector = None if detector is None else detector.to(self.device).eval()
        self.segmenter = segmenter.to(self.device).eval()
        self.mean_db, self.std_db = float(mean_db), float(std_db)
        self.score_threshold = score_threshold
        self.max_objects = max_objects
        if object_centre not in OBJECT_CENTRES:
            raise ValueError(f"object_centre must be one of {OBJECT_CENTRES}, got {object_centre!r}")
        self.object_centre = object_centre
        self.region_config = region_config or RegionGrowingConfig.for_profile(self.profile)
        # The detector's Doppler passes a 1x1 compression of D bins to 3 channels: refine it from the cube
        # (radar.doppler; None keeps the detector's own estimate).
        self.doppler_refinement = doppler_refinement
        n_range, n_angle, n_doppler = self.profile.shape
        self._run_detector: nn.Module | None = self.detector
        if frozen_detector and callable(getattr(self.detector, "decode", None)):
            self._run_detector = FrozenDetector(self.detector, (1, n_doppler, n_range, n_angle), self.device)
        self._detector_counter = None if self.detector is None else ComputeCounter(self.detector)
        self.params = {"detector": 0 if self.detector is None else count_params(self.detector),
                       "segmenter": count_params(self.segmenter)}
        self._segmenter_layers = counted_layers(self.segmenter)  # hooked for each frame's MAC count (eager)
        self._fused = FusedMinkUNet(self.segmenter) if fused_segmenter and fusable(self.segmenter) else None

    @classmethod
    def from_checkpoints(cls, detector: str | Path | Checkpoint, segmenter: str | Path | Checkpoint, *,
                         device: str | torch.device = "cpu", **kwargs: Any) -> EraseNet:
        """Both stages from checkpoints that carry their own architecture; the detector's checkpoint
        gives the preset, class names and input normalisation. A swapped pair, the same file twice or a
        checkpoint of another stage raises CheckpointError naming what was given and what was expected."""
        det, seg = load_pair(detector, segmenter)
        if det.preset != seg.preset:
            raise UserError(f"detector is for preset {det.preset!r} but segmenter for {seg.preset!r}")
        # A radar described by a file travels in the checkpoint (extra["radar_file"], its file form).
        profile = det.profile
        for ckpt, what in ((det, "detector"), (seg, "segmenter")):
            if "schema" in ckpt.extra:
                check_schema(cube_schema(profile), ckpt.extra["schema"], what=f"{what} checkpoint")
        return cls(det.build(), seg.build(), profile, class_names=det.class_names,
                   mean_db=det.normalisation.get("mean", 0.0), std_db=det.normalisation.get("std", 1.0),
                   device=device, **kwargs)

    @property
    def segmenter_form(self) -> Any:
        """What :meth:`point_logits` runs the segmenter as: its fused inference form (or the one
        :meth:`use_segmenter_form` gave), None when the eager module runs."""
        return self._fused

    def use_segmenter_form(self, form: Any) -> None:
        """Run the segmenter as ``form`` from now on: called as the fused form is, ``form(sparse) -> (logits,
        MacTally)`` (e.g. :class:`models.quantized.segmenter.Int8MinkUNet`); its ``precision`` (default "float")
        becomes the model's."""
        self._fused = form
        self.precision = getattr(form, "precision", "float")

    @property
    def history_frames(self) -> int:
        """Earlier frames of the sequence the detector reads beside the cube (0: one frame)."""
        return int(getattr(self.detector, "history_frames", 0) or 0)

    def schema(self, content: str = "complex") -> dict[str, Any]:
        """The cube schema this model accepts (radar.schema)."""
        return cube_schema(self.profile, content)

    def detector_macs(self) -> int:
        """Detector MACs per frame (analytic, cached per input shape); 0 without a detector."""
        if self._detector_counter is None:
            return 0
        n_range, n_angle, n_doppler = self.profile.shape
        return self._detector_counter.report((1, n_doppler, n_range, n_angle)).macs

    @torch.no_grad()
    def segment(self, cube: np.ndarray, *, kind: InputKind = InputKind.complex, centres: Centres | None = None,
                schema: dict[str, Any] | None = None, views: bool = False,
                history: Sequence[np.ndarray | None] | None = None, keep_log_power: bool = False,
                priors: TrackPriors | None = None) -> SegmentationResult:
        """Segment one frame: a RAD cube (R, A, D) holding ``kind`` (complex, its magnitude, or its log power in dB;
        radar.input_kind), whose dtype must fit that kind.

        ``centres`` (optional) replaces the detector (which then does not run and costs nothing): for
        evaluating stage 2 from the true centres, or a non-learned detector such as CFAR.
        ``schema`` (optional) is the cube's own description; a mismatch with the model's raises
        :class:`radar.schema.SchemaMismatch` naming every difference. ``views``: also return the input's RA and
        RD views in dB (``SegmentationResult.views``), from the frame's log power, inside the timed work.
        ``history`` (optional, for a detector with :attr:`history_frames`): the earlier frames' log power (R, A, D)
        dB, the latest first, None for one that does not exist; without it the detector sees a single cube.
        ``keep_log_power``: return the frame's log power too (``SegmentationResult.log_power``).
        ``priors`` (optional): where confirmed tracks expect their objects (:mod:`radar.track_priors`); a prediction
        with no centre near it is seeded from the detector's best centre near it above the priors' lower score
        (``SegmentationResult.prior_seeds`` counts them).
        """
        if priors is not None and centres is not None:
            raise ValueError("priors read the detector's heatmap: give no centres= with them")
        if schema is not None:
            check_schema(self.schema(SCHEMA_CONTENT[kind]), schema)
        if centres is None and self._run_detector is None:
            raise ValueError("this EraseNet has no detector: give the centres as centres=")
        kind = resolve_kind(cube.dtype, kind, flag="kind={}")
        if cube.shape != self.profile.shape:
            raise ValueError(f"cube must have shape {self.profile.shape} for preset {self.profile.name!r}, "
                             f"got {cube.shape}")
        seconds: dict[str, float] = {}
        # Log power that is not float32 is converted into a new buffer: the detector's input is normalised in that
        # buffer and the log power converted into it again after detection (one float32 cube at a time, not two).
        one_buffer = (centres is None and self.normalises_detector_input and kind is InputKind.log_power
                      and cube.dtype != np.float32)
        with _stage(seconds, "transform"):
            log_power = transforms.to_log_power(cube, kind)
            x = self._detector_input(log_power, in_place=one_buffer) if centres is None else None
        detect_macs = prior_seeds = 0
        if centres is None:
            with _stage(seconds, "detect"):
                outputs = self._detector_outputs(x, history)
                del x
            if one_buffer:
                with _stage(seconds, "transform"):
                    np.copyto(log_power, cube)
            with _stage(seconds, "detect"):
                lowest = self.score_threshold if priors is None else min(self.score_threshold,
                                                                         priors.config.threshold)
                centres, prior_seeds = centres_with_priors(self._decode(outputs, log_power, lowest),
                                                           self.score_threshold, priors, self.profile)
                detect_macs = self.detector_macs()
        with _stage(seconds, "grow"):
            regions = grow_regions(log_power, centres, self.profile, self.region_config)
        with _stage(seconds, "segment"):
            voxel_classes, segment_macs, segment_executed = self._segment_voxels(regions, log_power)
        with _stage(seconds, "project"):
            labels = np.zeros(self.profile.shape, np.uint8)
            labels[tuple(regions.voxels.T)] = voxel_classes
            # Background everywhere outside the ROI: project the ROI voxels alone.
            shape, num_classes = self.profile.shape, self.profile.num_classes
            ra_mask = transforms.project_voxels(regions.voxels, voxel_classes, shape, 2, num_classes)
            rd_mask = transforms.project_voxels(regions.voxels, voxel_classes, shape, 1, num_classes)
            objects = self._objects(regions, voxel_classes, centres)
            input_views = ((transforms.ra_view(log_power, kind=InputKind.log_power),
                            transforms.rd_view(log_power, kind=InputKind.log_power)) if views else None)
        compute = FrameCompute(
            detect_macs=detect_macs, segment_macs=segment_macs, segment_executed_macs=segment_executed,
            detector_params=self.params["detector"], segmenter_params=self.params["segmenter"],
            seconds={name: seconds.get(name, 0.0) for name in STEPS}, roi_voxels=len(regions),
            visited_points=regions.visited, detections=len(centres), runtime=self.runtime)
        return SegmentationResult(labels, ra_mask, rd_mask, objects, centres, regions, compute, input_views,
                                  log_power if keep_log_power else None, prior_seeds)

    @torch.no_grad()
    def detect(self, log_power: np.ndarray, *, score_threshold: float | None = None,
               history: Sequence[np.ndarray | None] | None = None) -> Centres:
        """The centres of one frame's log power (R, A, D) dB down to ``score_threshold`` (default the model's), found
        by the detector :meth:`segment` runs (this engine's: the ONNX graph, float or int8, or the PyTorch module),
        Doppler refined as :meth:`segment` refines it: what detection AP scores. ``history`` as in :meth:`segment`."""
        if self._run_detector is None:
            raise ValueError("this EraseNet has no detector")
        log_power = log_power.astype(np.float32, copy=False)
        threshold = self.score_threshold if score_threshold is None else score_threshold
        return self._centres(self._detector_input(log_power), log_power, threshold, history)

    def _centres(self, x: Any, log_power: np.ndarray, score_threshold: float,
                 history: Sequence[np.ndarray | None] | None = None) -> Centres:
        """The detector on its input ``x`` (and the earlier frames, if any), decoded down to ``score_threshold``,
        Doppler refined from ``log_power``."""
        return self._decode(self._detector_outputs(x, history), log_power, score_threshold)

    def _detector_outputs(self, x: Any, history: Sequence[np.ndarray | None] | None = None) -> Any:
        """The detector's outputs on its input ``x`` and the earlier frames, if any."""
        return self._run_detector(x) if history is None else self._run_detector(x, **self._history_input(history))

    def _decode(self, outputs: Any, log_power: np.ndarray, score_threshold: float) -> Centres:
        """The centres of the detector's ``outputs`` down to ``score_threshold``, Doppler refined from ``log_power``."""
        return decode_centres(self._run_detector, outputs, [log_power], k=self.max_objects,
                              score_threshold=score_threshold, doppler_refinement=self.doppler_refinement)[0]

    def _earlier_frames(self, history: Sequence[np.ndarray | None]) -> list[np.ndarray | None]:
        """``history`` (log power (R, A, D) dB or None where absent) checked against the detector, which reads at
        most ``history_frames`` earlier frames of the cube's shape, and padded with None to ``history_frames``.

        Raises:
            ValueError: a detector that reads one frame, more frames than it reads, or a frame of another shape.
        """
        n_history = self.history_frames
        if not n_history:
            raise ValueError("this model's detector reads one frame (history_frames 0): give no history")
        if len(history) > n_history:
            raise ValueError(f"{len(history)} earlier frames given, the detector reads {n_history}")
        shape = self.profile.shape
        for frame in history:
            if frame is not None and frame.shape != shape:
                raise ValueError(f"an earlier frame must have the cube's shape {shape}, got {frame.shape}")
        return [*history, *[None] * (n_history - len(history))]

    def _history_input(self, history: Sequence[np.ndarray | None]) -> dict[str, torch.Tensor]:
        """The detector's ``history`` (1, H, D, R, A), normalised, zero where absent, and ``history_present`` (1, H)."""
        frames = self._earlier_frames(history)
        zeros = torch.zeros(self.profile.n_doppler, *self.profile.shape[:2], device=self.device)
        earlier = [zeros if frame is None else self._detector_input(frame.astype(np.float32, copy=False))[0]
                   for frame in frames]
        present = torch.tensor([[frame is not None for frame in frames]], device=self.device)
        return {"history": torch.stack(earlier)[None], "history_present": present}

    def _detector_input(self, log_power: np.ndarray, *, in_place: bool = False) -> torch.Tensor:
        """The detector's input (1, D, R, A), normalised, from log power (R, A, D) dB; ``in_place``: normalised in
        ``log_power``'s own buffer (on the CPU), which then no longer holds the log power."""
        # (1, R, A, D) seen as (1, D, R, A) is channels_last: no transposing copy; one normalising pass.
        cube_view = torch.from_numpy(log_power).to(self.device)[None].permute(0, 3, 1, 2)
        return normalise_log_power(cube_view, self.mean_db, self.std_db,
                                   out=cube_view if in_place else torch.empty_like(cube_view))

    def _segment_voxels(self, regions: Regions, log_power: np.ndarray) -> tuple[np.ndarray, int, int]:
        """Class of every ROI voxel (N,) uint8 and the segmenter's useful and executed MACs."""
        if len(regions) == 0:
            return np.zeros(0, np.uint8), 0, 0
        logits, inverse, macs, executed = self.point_logits(regions, log_power)
        classes = logits.argmax(dim=1).to(torch.uint8).cpu().numpy()
        return classes[inverse], macs, executed

    @torch.no_grad()
    def point_logits(self, regions: Regions, log_power: np.ndarray) -> tuple[torch.Tensor, np.ndarray, int, int]:
        """The segmenter's class logits of a non-empty ROI: ``(P, C)`` over its points (:func:`radar.roi.roi_points`),
        ``inverse`` (N,) the point of each ROI voxel, and the useful and executed MACs."""
        points = roi_points(regions.voxels, log_power, self.profile, mean_db=self.mean_db, std_db=self.std_db)
        feats = torch.from_numpy(points.features).to(self.device)
        coords = torch.from_numpy(points.coords).to(self.device)
        batch = torch.zeros(len(coords), dtype=torch.int64, device=self.device)
        sparse = self.segmenter.make_input(torch.cat([batch[:, None], coords], dim=1), feats)
        if self._fused is not None:
            logits, tally = self._fused(sparse)
            macs, executed = tally.useful, tally.executed
        else:
            with MacRecorder(self.segmenter, layers=self._segmenter_layers,
                             params=self.params["segmenter"]) as recorder:
                logits = self.segmenter(sparse)
            report = recorder.report()
            macs, executed = report.macs, report.executed
        return logits, points.inverse, macs, executed

    def _objects(self, regions: Regions, voxel_classes: np.ndarray, centres: Centres) -> list[SegmentedObject]:
        """One object per seed whose region holds foreground voxels; class by majority vote of those voxels, position
        and radial velocity by ``object_centre``."""
        objects = []
        cart_x, cart_y = self.profile.ra_cartesian
        for seed, score in enumerate(centres.score):
            own = (regions.seed_index == seed) & (voxel_classes > 0)
            if not own.any():
                continue
            classes = voxel_classes[own]
            class_id = int(np.bincount(classes, minlength=self.profile.num_classes)[1:].argmax() + 1)
            if self.object_centre == "seed":
                x, y = (float(v) for v in self.profile.xy(centres.range_bin[seed], centres.angle_bin[seed]))
                doppler = float(centres.doppler_bin[seed])
            else:
                r, a, d = regions.voxels[own].T
                x, y = float(cart_x[r, a].mean()), float(cart_y[r, a].mean())
                phase = 2 * np.pi * d / self.profile.n_doppler  # circular mean: the Doppler axis wraps
                doppler = np.mod(np.angle(np.exp(1j * phase).mean()) / (2 * np.pi) * self.profile.n_doppler,
                                 self.profile.n_doppler)
            objects.append(SegmentedObject(
                class_id=class_id, class_name=self.class_names[class_id], score=float(score),
                range_m=float(np.hypot(x, y)), angle_deg=float(np.degrees(np.arctan2(x, y))),
                velocity_mps=float(self.profile.velocity_mps(doppler)), x=x, y=y, n_voxels=int(own.sum()),
            ))
        return objects
