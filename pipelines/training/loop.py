"""The one training loop: resume, time/step budget, best/last checkpoints, ``metrics.jsonl``, the
slimming penalty, and Ray Train's data-parallel world, for every :class:`~pipelines.training.task.Task`.

Run directory: ``config.json`` (the resolved configuration), ``metrics.jsonl`` (one JSON line per epoch:
train losses, lr, seconds, frames/s, training CPU seconds so far ``cpu_s``, validation figures), ``curve.jsonl``
(with ``curve_every``: a validation before the first step, every ``curve_every`` steps and at each epoch's end,
against training CPU seconds: learning curves), ``last.pt`` (model, optimiser and scheduler
state: ``--resume`` continues from it), ``model.pt`` (weights of the epoch with the best validation
score). Epochs are shuffled from ``(seed, epoch)``, so a resumed run sees the same order as a straight one.
A run that fails before its first epoch is saved removes the run directory it created.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, DistributedSampler

from models.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from models.slimming.penalty import slimming_penalty
from pipelines.datasets.store import frames_of_split, open_store
from pipelines.datasets.store_info import StoreInfo
from pipelines.progress import progress
from pipelines.ray_runtime import init_ray
from pipelines.training.config import TrainConfig
from pipelines.training.optim import make_optimizer, make_scheduler, resolve_device
from pipelines.training.task import Task, unwrap
from pipelines.training.tasks import task_for
from radar.errors import UserError
from radar.profiles import describe_for_storage

log = logging.getLogger(__name__)

RAY_OBJECT_STORE_BYTES = 200_000_000


# --------------------------------------------------------------------------- data-parallel world
class World:
    """The single-process world: rank 0 of 1. The Ray Train world overrides these."""

    rank = 0
    size = 1

    def wrap(self, model: nn.Module) -> nn.Module:
        return model

    def report(self, metrics: dict[str, Any]) -> None:
        pass


class RayWorld(World):
    """A Ray Train worker: rank and size from the train context; DDP via ``prepare_model``."""

    def __init__(self) -> None:
        import ray.train

        context = ray.train.get_context()
        self.rank = context.get_world_rank()
        self.size = context.get_world_size()

    def wrap(self, model: nn.Module) -> nn.Module:
        import ray.train.torch

        return ray.train.torch.prepare_model(model, move_to_device=False)

    def report(self, metrics: dict[str, Any]) -> None:
        import ray.train

        ray.train.report({k: v for k, v in metrics.items() if isinstance(v, int | float)})


class Budget:
    """When a run stops early: after ``max_steps`` optimiser steps or ``max_minutes`` of training in all
    (``spent_s``: time a resumed run had already used; measured from construction)."""

    def __init__(self, max_steps: int | None, max_minutes: float | None, *, spent_s: float = 0.0) -> None:
        self.max_steps = max_steps
        self.deadline = None if max_minutes is None else time.perf_counter() + 60.0 * max_minutes - spent_s

    def spent(self, step: int) -> bool:
        return ((self.max_steps is not None and step >= self.max_steps)
                or (self.deadline is not None and time.perf_counter() >= self.deadline))


class CpuClock:
    """Training CPU seconds of this process (all its threads): time spent inside :meth:`paused` (validation) is
    not counted; ``spent_s`` is what a resumed run had already used."""

    def __init__(self, spent_s: float = 0.0) -> None:
        self._origin = time.process_time() - spent_s

    def seconds(self) -> float:
        return time.process_time() - self._origin

    @contextmanager
    def paused(self) -> Iterator[None]:
        started = time.process_time()
        try:
            yield
        finally:
            self._origin += time.process_time() - started


# --------------------------------------------------------------------------- the loop
def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else float("nan")


def _append_line(path: Path, record: dict[str, Any]) -> None:
    with path.open("a") as fh:
        fh.write(json.dumps(record) + "\n")


def _keep_curve_until(path: Path, step: int) -> None:
    """A resumed run repeats the steps after its last checkpoint: drop their curve points."""
    if path.is_file():
        lines = [line for line in path.read_text().splitlines() if line and json.loads(line)["step"] <= step]
        path.write_text("".join(line + "\n" for line in lines))


def _curve_point(task: Task, model: nn.Module, device: torch.device, clock: CpuClock, *, epoch: float, step: int,
                 elapsed_s: float) -> dict[str, Any]:
    """Validation figures at this point of training, with the training CPU seconds spent to reach it."""
    cpu_s = clock.seconds()
    started = time.perf_counter()
    with clock.paused():
        figures = task.validate(unwrap(model), device)
    return {"epoch": epoch, "step": step, "cpu_s": cpu_s, "elapsed_s": elapsed_s, **figures,
            "seconds_validation": time.perf_counter() - started}


class _Curve:
    """Learning-curve points into ``path`` (``curve.jsonl``) when ``every`` > 0: the initial weights, every
    ``every`` steps inside an epoch (``between``) and each epoch's end (``append``, from the epoch's validation)."""

    def __init__(self, path: Path, every: int, steps_per_epoch: int, measure: Callable[..., dict[str, Any]],
                 step: int) -> None:
        self.path, self.every, self.steps_per_epoch, self.measure = path, every, steps_per_epoch, measure
        if every:
            _keep_curve_until(path, step)
            if step == 0:  # the curve's first point: the initial (or --init) weights
                self.append(measure(epoch=0, step=0, elapsed_s=0.0))

    def between(self, epoch: int, step: int, elapsed_s: float) -> None:
        within = step % self.steps_per_epoch
        if self.every and step % self.every == 0 and within:  # epoch ends are scored by the epoch's validation
            self.append(self.measure(epoch=epoch + within / self.steps_per_epoch, step=step, elapsed_s=elapsed_s))

    def append(self, point: dict[str, Any]) -> None:
        if self.every:
            _append_line(self.path, point)


def _checkpoint(task: Task, model: nn.Module, extra: dict[str, Any]) -> Checkpoint:
    state = {k: v.detach().cpu().contiguous().clone() for k, v in unwrap(model).state_dict().items()}
    return Checkpoint(model_name=task.hyper.model, config=task.model_config(), state_dict=state,
                      preset=task.store.profile.name, class_names=task.store.class_names,
                      normalisation=task.normalisation(),
                      extra={"stage": task.stage, "recipe": task.cfg.recipe, **_radar_description(task),
                             **task.extra(), **extra})


def _radar_description(task: Task) -> dict[str, Any]:
    """``{"radar_file": ...}`` for a radar described by a file (the checkpoint carries it), else nothing."""
    description = describe_for_storage(task.store.profile)
    return {} if description is None else {"radar_file": description}


def _check_run_dir(cfg: TrainConfig, run_dir: Path, hyper: Any) -> None:
    """Refuse to overwrite a run, or to resume one trained with other settings; write ``config.json``."""
    config_path = run_dir / "config.json"
    if (run_dir / "last.pt").exists() and not cfg.resume:
        raise FileExistsError(f"{run_dir} already holds a run (last.pt); pass --resume to continue it "
                              "or choose another --out")
    if cfg.resume and config_path.is_file():
        saved = json.loads(config_path.read_text())
        saved.pop("resolved", None)
        before = TrainConfig.from_dict(saved).identity()
        if before != cfg.identity():
            changed = sorted(k for k in before if before[k] != cfg.identity()[k])
            raise UserError(f"--resume: {run_dir} was trained with other settings ({', '.join(changed)})")
    run_dir.mkdir(parents=True, exist_ok=True)
    config_path.write_text(json.dumps({**cfg.to_dict(), "resolved": dataclasses.asdict(hyper)}, indent=2))


MIN_TRAIN_FRAMES = 600
"""Fewer train frames than this draw a warning: on the example radar of README's "Bring your own radar" a detector
trained on 84 frames scored test mAP 0.03 (no seed above the threshold), one trained on 630 frames 0.455."""


def _check_splits(cfg: TrainConfig) -> None:
    """An empty validation split would make an unvalidated model "the best": refuse it, saying what to do. A train
    split too small to learn from is allowed (smoke runs, tests) but warned about."""
    root = open_store(cfg.store)
    if cfg.val_split and len(frames_of_split(root, cfg.val_split)) == 0:
        raise UserError(f"split {cfg.val_split!r} of {cfg.store} has no frames, so no epoch could be validated; "
                         "preprocess more sequences (--split-fractions), or pass --val-split none to keep the last "
                         "epoch as model.pt")
    n_train = len(frames_of_split(root, "train"))
    if n_train < MIN_TRAIN_FRAMES:
        log.warning("%s holds %d train frames: too few for the model to learn (at least %d; on a new radar a "
                    "detector trained on 84 frames scored test mAP 0.03, on 630 frames 0.455); preprocess more "
                    "sequences",
                    cfg.store, n_train, MIN_TRAIN_FRAMES)


def train_loop(cfg: TrainConfig, world: World | None = None) -> dict[str, Any]:
    """Train ``cfg`` in this process (rank ``world.rank`` of ``world.size``) with its stage's task; returns the
    last epoch's metrics."""
    world = world or World()
    run_dir = Path(cfg.out)
    created = not run_dir.exists()
    try:
        return _train(cfg, task_for(cfg.stage), world, run_dir)
    except BaseException:
        if created and world.rank == 0 and not (run_dir / "last.pt").exists():
            shutil.rmtree(run_dir, ignore_errors=True)  # no half-written run directory
        raise


def _train(cfg: TrainConfig, task_class: type[Task], world: World, run_dir: Path) -> dict[str, Any]:
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    store = StoreInfo.read(cfg.store)
    _check_splits(cfg)
    init, hyper = _init_checkpoint(cfg, store)
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    last_path = run_dir / "last.pt"
    if world.rank == 0:
        _check_run_dir(cfg, run_dir, hyper)

    task = task_class(cfg, hyper, store, run_dir)
    model = task.build_model().to(device)
    if init is not None:
        model.load_state_dict(init.state_dict)
    task.prepare(model, world.rank)
    optimizer = make_optimizer(hyper, model.parameters())
    dataset = task.train_dataset()
    if len(dataset) < world.size * hyper.batch_size:
        raise UserError(f"split {cfg.train_split!r} of {cfg.store} has {len(dataset)} usable frames, fewer than "
                         f"one batch of {hyper.batch_size} per worker ({world.size} workers)")
    sampler = DistributedSampler(dataset, num_replicas=world.size, rank=world.rank, shuffle=True, seed=cfg.seed,
                                 drop_last=True)
    loader = DataLoader(dataset, batch_size=hyper.batch_size, sampler=sampler, collate_fn=task.collate,
                        num_workers=cfg.workers, drop_last=True)  # drop_last: BatchNorm at P7 needs >= 2
    per_step = hyper.schedule == "cosine"
    scheduler = make_scheduler(hyper, optimizer, len(loader))

    start_epoch, step, best, elapsed, cpu_spent = 0, 0, -math.inf, 0.0, 0.0
    if cfg.resume and last_path.is_file():
        start_epoch, step, best, elapsed, cpu_spent = _resume(last_path, model, optimizer, scheduler)
    model = world.wrap(model)
    model.train()

    metrics: dict[str, Any] = {}
    clock = CpuClock(cpu_spent)
    curve = _Curve(run_dir / "curve.jsonl", cfg.curve_every if world.rank == 0 else 0, len(loader),
                   lambda **at: _curve_point(task, model, device, clock, **at), step)
    budget = Budget(cfg.max_steps, cfg.max_minutes, spent_s=elapsed)
    name = cfg.model or hyper.model
    for epoch in range(start_epoch, hyper.epochs):
        if budget.spent(step):
            break
        sampler.set_epoch(epoch)
        if hasattr(dataset, "set_epoch"):
            dataset.set_epoch(epoch)
        started = time.perf_counter()
        bar = progress(loader, desc=f"{name} epoch {epoch + 1}/{hyper.epochs}", unit="batch", leave=False,
                   disable=not cfg.progress or world.rank != 0, dynamic_ncols=True)
        step, losses, samples = _run_epoch(
            cfg, task, model, bar, (optimizer, scheduler if per_step else None), device, world, budget, step,
            after_step=lambda done, e=epoch, t0=started - elapsed: curve.between(e, done, time.perf_counter() - t0))
        if not per_step:
            scheduler.step()
        seconds = time.perf_counter() - started
        metrics = {"epoch": epoch + 1, "step": step, "lr": optimizer.param_groups[0]["lr"],
                   **{f"train_{k}": _mean(v) for k, v in losses.items()}, "seconds": seconds,
                   "frames_per_second": samples / max(seconds, 1e-9)}
        if world.rank == 0:
            point = _curve_point(task, model, device, clock, step=step,
                                 epoch=epoch + (step % len(loader)) / len(loader) if step % len(loader) else epoch + 1,
                                 elapsed_s=elapsed + time.perf_counter() - started)
            metrics.update({k: v for k, v in point.items() if k not in ("epoch", "step", "elapsed_s")})
            elapsed += time.perf_counter() - started
            metrics["elapsed_s"] = elapsed  # training + validation time of the whole run so far
            best = _save_epoch(task, model, (optimizer, scheduler), metrics, best, run_dir)
            curve.append({**point, "elapsed_s": elapsed})
            log.info("%s epoch %d: %s", name, epoch + 1,
                     ", ".join(f"{k} {v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
        world.report(metrics)
    return metrics


def _init_checkpoint(cfg: TrainConfig, store: StoreInfo) -> tuple[Checkpoint | None, Any]:
    """The ``--init`` checkpoint (checked against the store and ``--model``) and the resolved hyper-parameters,
    with the checkpoint's architecture (a pruned one carries its channels table)."""
    hyper = cfg.hyper()
    if not cfg.init:
        return None, hyper
    init = load_checkpoint(cfg.init)
    if init.preset != store.profile.name:
        raise UserError(f"--init {cfg.init} is for preset {init.preset!r}, the store for {store.profile.name!r}")
    if cfg.model is not None and cfg.model != init.model_name:
        raise UserError(f"--init {cfg.init} holds {init.model_name}, not {cfg.model}")
    return init, dataclasses.replace(hyper, model=init.model_name,
                                     model_config={k: v for k, v in init.config.items() if k not in ("preset", "view")})


def _resume(last_path: Path, model: nn.Module, optimizer: Any, scheduler: Any
            ) -> tuple[int, int, float, float, float]:
    """Load ``last.pt`` into the model, optimiser and scheduler; ``(epoch, step, best, elapsed seconds, training
    CPU seconds)``."""
    state = load_checkpoint(last_path)
    model.load_state_dict(state.state_dict)
    optimizer.load_state_dict(state.extra["optimizer"])
    scheduler.load_state_dict(state.extra["scheduler"])
    start_epoch, step, best = int(state.extra["epoch"]), int(state.extra["step"]), float(state.extra["best"])
    log.info("resumed %s at epoch %d, step %d", last_path.parent, start_epoch, step)
    return (start_epoch, step, best, float(state.extra.get("elapsed_s", 0.0)),
            float(state.extra.get("cpu_s", 0.0)))


def _run_epoch(cfg: TrainConfig, task: Task, model: nn.Module, bar: Any, stepping: tuple[Any, Any],
               device: torch.device, world: World, budget: Budget, step: int,
               after_step: Callable[[int], None] | None = None) -> tuple[int, dict[str, list[float]], int]:
    """One pass over ``bar`` (the loader), stopping early when the budget is spent; ``(step, losses per name,
    frames seen)``. ``stepping``: the optimiser and the scheduler when it steps per optimiser step (else None);
    ``after_step(step)`` runs after every step that did not spend the budget."""
    optimizer, per_step_scheduler = stepping
    losses: dict[str, list[float]] = {}
    samples, started = 0, time.perf_counter()
    for batch in bar:
        named = task.loss(model, batch, device)
        if cfg.slim_lambda:  # network slimming: L1 on every BatchNorm scale
            named["slim_l1"] = cfg.slim_lambda * slimming_penalty(unwrap(model))
            named["total"] = named["total"] + named["slim_l1"]
        optimizer.zero_grad(set_to_none=True)
        named["total"].backward()
        optimizer.step()
        if per_step_scheduler is not None:
            per_step_scheduler.step()
        step += 1
        samples += task.batch_size_of(batch) * world.size
        for key, value in named.items():
            losses.setdefault(key, []).append(float(value.detach()))
        rate = samples / max(time.perf_counter() - started, 1e-9)
        bar.set_postfix(loss=f"{_mean(losses['total'][-20:]):.4f}", frames_s=f"{rate:.1f}")
        if budget.spent(step):
            break
        if after_step is not None:
            after_step(step)
    bar.close()
    return step, losses, samples


def _save_epoch(task: Task, model: nn.Module, stepping: tuple[Any, Any], metrics: dict[str, Any], best: float,
                run_dir: Path) -> float:
    """Rank 0 after validation: ``model.pt`` when the monitored score improved, ``last.pt`` always, a line of
    ``metrics.jsonl``; sets ``metrics["best"]``; returns the best score so far."""
    optimizer, scheduler = stepping
    epoch, step = metrics["epoch"], metrics["step"]
    score = metrics.get(task.monitor, float("nan"))
    # without a validation split (--val-split none) every epoch is "best": model.pt is the latest; with one,
    # only a strictly better score is (a run whose mAP stays 0.0 keeps its first epoch as the best)
    improved = not math.isfinite(score) or score > best
    if improved:
        best = score if math.isfinite(score) else best
        save_checkpoint(_checkpoint(task, model, {"epoch": epoch, "step": step, "metrics": metrics}),
                        run_dir / "model.pt")
    metrics["best"] = improved
    save_checkpoint(_checkpoint(task, model, {
        "epoch": epoch, "step": step, "best": best, "elapsed_s": metrics["elapsed_s"], "cpu_s": metrics["cpu_s"],
        "metrics": metrics, "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()}),
        run_dir / "last.pt")
    _append_line(run_dir / "metrics.jsonl", metrics)
    return best


# --------------------------------------------------------------------------- Ray Train
def _ray_worker(config: dict[str, Any]) -> None:
    """Ray Train's per-worker function: the same loop, in a data-parallel world."""
    torch.set_num_threads(max(1, int(config.get("threads", 1))))
    train_loop(TrainConfig.from_dict(config["cfg"]), RayWorld())


def run_ray_train(cfg: TrainConfig) -> dict[str, Any]:
    """``cfg.ray_workers`` data-parallel workers under Ray Train's TorchTrainer (gloo on CPU, NCCL on GPU)."""
    import ray
    from ray.train import RunConfig, ScalingConfig
    from ray.train.torch import TorchConfig, TorchTrainer

    started_here = init_ray(cfg.address, num_cpus=max(2, cfg.ray_workers), object_store_bytes=RAY_OBJECT_STORE_BYTES)
    try:
        run_dir = Path(cfg.out).resolve()
        run_dir.mkdir(parents=True, exist_ok=True)
        use_gpu = resolve_device(cfg.device).type == "cuda"
        worker_cfg = dataclasses.replace(cfg, out=str(run_dir), store=str(Path(cfg.store).resolve()),
                                         device="cuda" if use_gpu else "cpu", ray_workers=0)
        trainer = TorchTrainer(
            _ray_worker,
            train_loop_config={"cfg": worker_cfg.to_dict(), "threads": 1},
            torch_config=TorchConfig(backend="nccl" if use_gpu else "gloo"),
            scaling_config=ScalingConfig(num_workers=cfg.ray_workers, use_gpu=use_gpu),
            run_config=RunConfig(name=f"train-{cfg.stage}", storage_path=str(run_dir / "ray")),
        )
        result = trainer.fit()
        if result.error is not None:
            raise result.error
        # rank 0 wrote every epoch's metrics; Ray's result keeps only what came with a Ray checkpoint
        lines = (run_dir / "metrics.jsonl").read_text().splitlines()
        return json.loads(lines[-1]) if lines else {}
    finally:
        if started_here:
            ray.shutdown()


def train(cfg: TrainConfig) -> dict[str, Any]:
    """Run a training job (Ray Train when ``cfg.ray_workers``); returns the last epoch's metrics and where the
    run lives."""
    started = time.perf_counter()
    metrics = run_ray_train(cfg) if cfg.ray_workers else train_loop(cfg)
    return {"run": str(cfg.out), "checkpoint": str(Path(cfg.out) / "model.pt"),
            "seconds": time.perf_counter() - started, "metrics": metrics}
