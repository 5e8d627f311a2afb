"""The task of each stage, by the stage's name (:class:`models.capabilities.Stage`)."""

from __future__ import annotations

from pipelines.training.baselines import BaselineTask
from pipelines.training.detector import DetectorTask
from pipelines.training.segmenter import SegmenterTask
from pipelines.training.task import Task

TASKS: dict[str, type[Task]] = {task.stage: task for task in (DetectorTask, SegmenterTask, BaselineTask)}


def task_for(stage: str) -> type[Task]:
    try:
        return TASKS[stage]
    except KeyError:
        raise ValueError(f"stage must be one of {sorted(TASKS)}, got {stage!r}") from None
