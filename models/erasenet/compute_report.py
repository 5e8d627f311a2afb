"""What one frame cost: :class:`FrameCompute`, built by :meth:`models.erasenet.model.EraseNet.segment`.

One typed report crosses from ``models/`` to its readers (the service's response and ledger, the CLI,
the evaluation and batch reports): MACs per stage (useful, and what the kernels executed), parameters per
network, wall-clock seconds per stage, the ROI's size. Totals are computed here, never by a reader. The
service adds its own stages (ADC processing, request decoding) with :meth:`FrameCompute.plus_seconds`,
which returns a new report.

:meth:`FrameCompute.to_dict` is the JSON form (``radarseg segment`` prints it; the service's ``compute``
block is the same with its own ``decode`` stage and without ``executed_macs``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

STEPS = ("transform", "detect", "grow", "segment", "project")
"""The stages of :meth:`models.erasenet.model.EraseNet.segment`, in order."""


@dataclass(frozen=True)
class FrameCompute:
    """One frame's cost. MACs per frame (correct convention, :mod:`models.compute`); seconds wall clock."""

    detect_macs: int  # 0 when the centres were given (the detector did not run)
    segment_macs: int  # useful MACs of the sparse segmenter on this ROI
    segment_executed_macs: int  # what its kernels ran (the GEMM path also multiplies missing neighbours' zeros)
    detector_params: int
    segmenter_params: int
    seconds: dict[str, float] = field(default_factory=dict)  # stage -> seconds, in pipeline order
    roi_voxels: int = 0
    visited_points: int = 0  # voxels region growing looked at
    detections: int = 0  # centres the ROI grew from (the API's compute.detections)
    runtime: str = "torch"  # what ran the networks (models.runtime.RUNTIMES)

    # ----- totals
    @property
    def macs_total(self) -> int:
        return self.detect_macs + self.segment_macs

    @property
    def executed_macs_total(self) -> int:
        return self.detect_macs + self.segment_executed_macs

    @property
    def params_total(self) -> int:
        return self.detector_params + self.segmenter_params

    @property
    def seconds_total(self) -> float:
        return sum(self.seconds.values())

    @property
    def compute_us(self) -> int:
        """Total seconds in integer microseconds (what the ledger bills, so sums are exact)."""
        return round(self.seconds_total * 1e6)

    # ----- the service's own stages
    def plus_seconds(self, stage: str, seconds: float, *, first: bool = False) -> FrameCompute:
        """A copy with ``seconds`` added to ``stage`` (a new stage goes last, or first with ``first``)."""
        if stage in self.seconds:
            timings = {**self.seconds, stage: self.seconds[stage] + seconds}
        elif first:
            timings = {stage: seconds, **self.seconds}
        else:
            timings = {**self.seconds, stage: seconds}
        return replace(self, seconds=timings)

    # ----- per-stage views (totals included) and the JSON form
    def macs_by_stage(self) -> dict[str, int]:
        return {"detect": self.detect_macs, "grow": 0, "segment": self.segment_macs, "total": self.macs_total}

    def executed_macs_by_stage(self) -> dict[str, int]:
        return {"detect": self.detect_macs, "segment": self.segment_executed_macs, "total": self.executed_macs_total}

    def params_by_network(self) -> dict[str, int]:
        return {"detector": self.detector_params, "segmenter": self.segmenter_params, "total": self.params_total}

    def seconds_by_stage(self, *, decimals: int | None = None) -> dict[str, float]:
        """Seconds per stage and ``total``; with ``decimals`` each stage rounded and the total the billed
        microseconds (the service's response)."""
        if decimals is None:
            return {**self.seconds, "total": self.seconds_total}
        return {**{k: round(v, decimals) for k, v in self.seconds.items()}, "total": self.compute_us / 1e6}

    def to_dict(self) -> dict[str, Any]:
        return {
            "macs": self.macs_by_stage(),
            "executed_macs": self.executed_macs_by_stage(),
            "params": self.params_by_network(),
            "seconds": self.seconds_by_stage(),
            "roi_voxels": self.roi_voxels,
            "visited_points": self.visited_points,
            "detections": self.detections,
            "runtime": self.runtime,
            "engine": self.runtime,  # the runtime's former name, kept for clients that read it
        }
