"""Compression sweep of network slimming (docs/design.md section 11): prune, optionally fine-tune, score.

The job follows :mod:`pipelines.jobs` (``add_arguments``, ``config_from_args``, ``main(cfg) -> dict``; the options
and the config in :mod:`pipelines.training.slim_sweep_options`)::

    python -m pipelines.training.slim_sweep --store STORE.zarr --detector DET.pt --minkunet SEG_M.pt \\
        --spvcnn SEG_S.pt \\
        --smvanet SMVA.pt [--ratios 0.1 0.3 0.4 0.6 0.7] [--split test] [--max-frames N] [--finetune-steps S]
    radarseg slim-sweep ...                                      # the same arguments

For every given checkpoint and every ratio (0 included: the unpruned reference) the checkpoint is pruned
with :func:`models.slimming.prune.prune_checkpoint` (one global BatchNorm-scale threshold), fine-tuned for
``--finetune-steps`` optimiser steps with ``--init`` (0: prune only; the paper fine-tunes 50 epochs at
lr 1e-3 for ERASE-Net and 1e-5 for the baselines, the defaults of ``--lr-*``), then scored on ``--split``:

- detector: AP at 1/3/5 m and mAP (the trainer's validation: :func:`pipelines.evaluation.scoring.score_detector`);
- ERASE-Net (M) / (S): the pruned MinkUNet / SPVCNN behind the *unpruned* detector, end to end with
  :func:`pipelines.evaluation.evaluate.evaluate` (RA and RD mIoU, background included; segmenter params and mean
  segmenter MACs per frame, which depend on the ROI);
- SMVA-Net: :func:`pipelines.training.train_baselines.score_baseline` (RA and RD mIoU), params and analytic MACs.

Writes ``OUT/slimming.md`` (tables in the paper's form, with the command and what was done),
``OUT/slimming.png`` (RA and RD mIoU against the parameters left, ERASE-Net (M), ERASE-Net (S), SMVA-Net)
and ``OUT/slimming.json`` (every figure); pruned checkpoints and fine-tune runs go to ``--work``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shlex
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import torch

from models.capabilities import Stage, dense_input_shapes, stage_of
from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.compute import count_macs
from models.slimming.prune import prune_checkpoint
from pipelines.datasets.store_info import StoreInfo
from pipelines.datasets.views import ViewDataset, load_baseline
from pipelines.evaluation.evaluate import EvaluateConfig, evaluate
from pipelines.evaluation.report import fmt_pct
from pipelines.evaluation.scoring import score_baseline, score_detector
from pipelines.jobs import run_module
from pipelines.training.config import DEFAULT_JITTER_STD, TrainConfig
from pipelines.training.loop import train
from pipelines.training.slim_sweep_options import (  # noqa: F401 (the job's options: pipelines.jobs' contract)
    PAPER_RATIOS,
    SLIMMED,
    SweepConfig,
    add_arguments,
    config_from_args,
)
from radar.errors import UserError

log = logging.getLogger(__name__)

SEGMENTERS = {"minkunet": "ERASE-Net (M)", "spvcnn": "ERASE-Net (S)"}


def score_detector_checkpoint(path: str | Path, cfg: SweepConfig) -> dict[str, float]:
    """AP@1/3/5 and mAP of a detector checkpoint on ``cfg.split`` (up to ``cfg.max_frames`` frames)."""
    store = StoreInfo.read(cfg.store)
    scores = score_detector(load_checkpoint(path).build(), cfg.store, cfg.split, store.profile, store.normalisation,
                            max_frames=cfg.max_frames)
    return {k: float(v) for k, v in scores.items() if k.startswith("AP") or k == "mAP"}


def score_segmenter(path: str | Path, cfg: SweepConfig, tag: str) -> dict[str, float]:
    """RA/RD mIoU of ERASE-Net with this segmenter behind the unpruned detector, and the segmenter's cost."""
    metrics = evaluate(EvaluateConfig(detector=cfg.detector, segmenter=str(path), store=cfg.store,
                                      out=str(Path(cfg.work) / f"eval-{tag}"), split=cfg.split,
                                      max_frames=cfg.max_frames, pictures=0, sweep=(), sweep_frames=0,
                                      oracle=False, progress=False))
    cost = metrics["cost"]
    return {"mIoU_RA": metrics["segmentation"]["RA"]["mIoU"], "mIoU_RD": metrics["segmentation"]["RD"]["mIoU"],
            "macs": float(cost["macs_mean"].get("segment", float("nan"))), "frames": metrics.get("frames")}


def score_smvanet(path: str | Path, cfg: SweepConfig) -> dict[str, float]:
    """RA/RD mIoU of a multi-view baseline and its analytic MACs (both counting conventions)."""
    model, checkpoint, stats = load_baseline(path)
    dataset = ViewDataset(cfg.store, cfg.split, n_frames=model.n_frames, stats=stats, limit=cfg.max_frames)
    scores = score_baseline(model, dataset, num_classes=len(checkpoint.class_names))
    report = count_macs(model, *dense_input_shapes(model, checkpoint.preset))
    return {"mIoU_RA": scores["mIoU_ra"], "mIoU_RD": scores["mIoU_rd"], "macs": float(report.macs),
            "macs_paper": float(report.macs_paper), "frames": scores["frames"]}


# --------------------------------------------------------------------------- fine-tuning
def finetune(kind: str, pruned: Path, run: Path, cfg: SweepConfig) -> Path:
    """``cfg.steps(kind)`` steps from the pruned checkpoint with the trainers' ``--init``; the last weights.

    ``run`` belongs to the sweep: a run left there by an earlier sweep is replaced."""
    shutil.rmtree(run, ignore_errors=True)
    stage = SLIMMED[kind]
    train(TrainConfig(stage=stage.value, model=load_checkpoint(pruned).model_name if stage is Stage.BASELINE else None,
                      store=cfg.store, out=str(run), init=str(pruned),
                      lr=cfg.lr_baseline if stage is Stage.BASELINE else cfg.lr_erasenet, epochs=10_000,
                      # the detector's deepest BatchNorm needs two frames (TrainConfig refuses batch 1 there)
                      batch_size=max(2, cfg.batch_size) if stage is Stage.DETECTOR else cfg.batch_size,
                      max_steps=cfg.steps(kind), val_split=None, seed=cfg.seed,
                      threads=cfg.threads, progress=False,
                      jitter_std=DEFAULT_JITTER_STD if stage is Stage.SEGMENTER else None))
    return run / "model.pt"  # without validation model.pt holds the latest weights


# --------------------------------------------------------------------------- the sweep
def _score(kind: str, path: Path, cfg: SweepConfig, tag: str) -> dict[str, float]:
    if SLIMMED[kind] is Stage.DETECTOR:
        return score_detector_checkpoint(path, cfg)
    if SLIMMED[kind] is Stage.BASELINE:
        return score_smvanet(path, cfg)
    return score_segmenter(path, cfg, tag)


def sweep_model(kind: str, path: str, cfg: SweepConfig) -> list[dict[str, Any]]:
    """Rows (one per ratio, 0 first) for one checkpoint.

    With fine-tuning, every ratio (0 included, so the reference gets the same extra steps) is scored after
    pruning and again after fine-tuning: keys ``pruned_<metric>`` hold the first scores.
    """
    checkpoint: Checkpoint = load_checkpoint(path)
    stage = stage_of(checkpoint.build())
    if stage is not SLIMMED[kind]:
        raise UserError(f"--{kind} {path}: expected a {SLIMMED[kind]} checkpoint, got a {stage} "
                         f"({checkpoint.model_name})")
    work = Path(cfg.work) / kind
    rows = []
    for ratio in sorted({0.0, *cfg.ratios}):
        started = time.perf_counter()
        tag = f"{kind}-r{ratio:.2f}"
        pruned, report = prune_checkpoint(checkpoint, ratio=ratio)
        scored = Path(path) if ratio == 0 else save_checkpoint(pruned, work / f"pruned-r{ratio:.2f}.pt")
        scores = _score(kind, scored, cfg, tag)
        if cfg.steps(kind):
            scores = {f"pruned_{k}": v for k, v in scores.items()}
            scored = finetune(kind, save_checkpoint(pruned, work / f"pruned-r{ratio:.2f}.pt"),
                              work / f"finetune-r{ratio:.2f}", cfg)
            scores.update(_score(kind, scored, cfg, f"{tag}-ft"))
        if report.macs_after is not None:
            scores.setdefault("macs", float(report.macs_after))
        rows.append({"model": kind, "ratio": ratio, "params": report.params_after, "finetune_steps": cfg.steps(kind),
                     "checkpoint": str(scored), "seconds": time.perf_counter() - started, **scores})
        log.info("%s ratio %.2f: %s", kind, ratio, {k: v for k, v in rows[-1].items() if isinstance(v, float)})
    return rows


def format_report(rows: list[dict[str, Any]], cfg: SweepConfig, command: str, seconds: float) -> str:
    """``slimming.md``: the detector table and the segmentation table in the paper's form."""

    def what(kind: str) -> str:
        steps = cfg.steps(kind)
        lr = cfg.lr_baseline if SLIMMED[kind] is Stage.BASELINE else cfg.lr_erasenet
        return (f"pruned, then fine-tuned for {steps} optimiser steps (batch {cfg.batch_size}, lr {lr:g})" if steps
                else "pruned only, **not fine-tuned**")

    kinds = list(dict.fromkeys(r["model"] for r in rows))
    lines = ["# Network slimming: compression sweep", "",
             f"Made by `{command}` in {seconds / 60:.1f} min on a shared 2-core CPU.", "",
             f"- Store `{cfg.store}`, split `{cfg.split}`, "
             f"{'all frames' if not cfg.max_frames else f'up to {cfg.max_frames} frames'} per model and ratio.",
             "- After pruning, each checkpoint was: " + "; ".join(f"{k} {what(k)}" for k in kinds)
             + " (the paper fine-tunes 50 epochs). Ratio 0 is the checkpoint as given, fine-tuned like the others "
             "when they are, so every row has had the same training.",
             "- Ratio = fraction of BatchNorm channels removed under one global "
             "threshold (`models/slimming/prune.py`); params are those of the genuinely narrower rebuilt model "
             "(all of them non-zero).",
             "- Segmenter rows run ERASE-Net end to end behind the *unpruned* detector; their MACs are the "
             "segmenter's mean per frame (ROI-dependent). SMVA-Net MACs are analytic per frame (FlopCounter "
             "convention; the paper's counter in brackets).", ""]
    lines += ["Input checkpoints: " + ", ".join(f"{k} `{getattr(cfg, k)}`" for k in kinds), ""]
    if cfg.notes:
        lines += [cfg.notes, ""]
    det = [r for r in rows if SLIMMED[r["model"]] is Stage.DETECTOR]
    if det:
        tuned = cfg.steps(det[0]["model"]) > 0
        lines += ["## Detector", "", "| ratio | params (M) | GMACs | AP@1 | AP@3 | AP@5 | mAP |"
                  + (" mAP before fine-tuning |" if tuned else ""),
                  "|---|---|---|---|---|---|---|" + ("---|" if tuned else "")]
        for r in det:
            ap = " | ".join(f"{r.get(k, float('nan')):.3f}" for k in ("AP@1", "AP@3", "AP@5", "mAP"))
            before = f" {r['pruned_mAP']:.3f} |" if tuned else ""
            lines.append(f"| {r['ratio']:.1f} | {r['params'] / 1e6:.3f} | {r['macs'] / 1e9:.3f} | {ap} |{before}")
        lines += ["", "Paper (NXP, 50-epoch fine-tunes), ratio 0/0.1/0.3/0.4/0.6/0.7: params "
                  "2.08/1.87/1.45/1.25/0.83/0.62 M, mAP 0.853/0.82/0.83/0.84/0.79/0.13.", ""]
    seg = [r for r in rows if SLIMMED[r["model"]] is not Stage.DETECTOR]
    if seg:
        lines += ["## Segmentation (mIoU %, background included)", "",
                  "| model | ratio | params (M) | GMACs | RA mIoU | RD mIoU | RA / RD before fine-tuning |",
                  "|---|---|---|---|---|---|---|"]
        for r in seg:
            name = SEGMENTERS.get(r["model"], "SMVA-Net")
            macs = f"{r['macs'] / 1e9:.4f}" + (f" [{r['macs_paper'] / 1e9:.4f}]" if "macs_paper" in r else "")
            before = (f"{fmt_pct(r['pruned_mIoU_RA'])} / {fmt_pct(r['pruned_mIoU_RD'])}" if "pruned_mIoU_RA" in r
                      else "(not fine-tuned)")
            lines.append(f"| {name} | {r['ratio']:.1f} | {r['params'] / 1e6:.3f} | {macs} | {fmt_pct(r['mIoU_RA'])} "
                         f"| {fmt_pct(r['mIoU_RD'])} | {before} |")
        lines += ["", "![mIoU against parameters](slimming.png)", ""]
    return "\n".join(lines)


def plot(rows: list[dict[str, Any]], path: Path) -> Path | None:
    """RA and RD mIoU against the parameters left, one line per segmentation model."""
    seg = [r for r in rows if SLIMMED[r["model"]] is not Stage.DETECTOR]
    if not seg:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for view, ax in zip(("RA", "RD"), axes, strict=True):
        for kind in dict.fromkeys(r["model"] for r in seg):
            points = sorted((r["params"] / 1e6, 100 * r[f"mIoU_{view}"], r["ratio"]) for r in seg if r["model"] == kind)
            ax.plot([p[0] for p in points], [p[1] for p in points], "o-", label=SEGMENTERS.get(kind, "SMVA-Net"))
            for x, y, ratio in points:
                ax.annotate(f"{ratio:.1f}", (x, y), fontsize=7, textcoords="offset points", xytext=(3, 3))
        ax.set_xscale("log")
        ax.set_xlabel("non-zero parameters (M)")
        ax.set_title(f"{view} view")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("mIoU (%)")
    axes[0].legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(cfg: SweepConfig, command: str | None = None) -> dict[str, Any]:
    """Run the sweep; returns the rows and where the table, plot and JSON were written."""
    torch.set_num_threads(max(1, cfg.threads))
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    for kind in SLIMMED:
        path = getattr(cfg, kind)
        if path:
            rows += sweep_model(kind, path, cfg)
    if not rows:
        raise UserError("give at least one checkpoint (--detector, --minkunet, --spvcnn, --smvanet)")
    seconds = time.perf_counter() - started
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    if command is None:
        program = "python -m pipelines.training.slim_sweep" if sys.argv[0].endswith(".py") else Path(sys.argv[0]).name
        command = " ".join([program, *(shlex.quote(a) for a in sys.argv[1:])])
    table = out / "slimming.md"
    table.write_text(format_report(rows, cfg, command, seconds))
    (out / "slimming.json").write_text(json.dumps({"config": dataclasses.asdict(cfg), "command": command,
                                                   "seconds": seconds, "rows": rows}, indent=2))
    return {"table": str(table), "plot": str(plot(rows, out / "slimming.png")), "rows": rows, "seconds": seconds}


def format_result(result: dict[str, Any]) -> str:
    return f"table: {result['table']}\nplot: {result['plot']}"


if __name__ == "__main__":
    sys.exit(run_module("pipelines.training.slim_sweep"))
