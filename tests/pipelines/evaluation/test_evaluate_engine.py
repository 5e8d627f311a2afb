"""evaluate takes the runtime it scores as a config field (``--engine``), checked before anything is loaded."""

from __future__ import annotations

import pytest

from pipelines.evaluation import evaluate as evaluate_job
from pipelines.evaluation.evaluate import EvaluateConfig
from pipelines.jobs import parse_config


def test_the_runtime_is_a_config_field_and_an_option():
    cfg = parse_config(evaluate_job, ["--detector", "d.pt", "--segmenter", "s.pt", "--store", "s.zarr", "--out", "o",
                                      "--engine", "onnx-int8"], "radarseg evaluate")
    assert cfg.engine == "onnx-int8" and cfg.onnx_dir is None
    assert EvaluateConfig("d.pt", "s.pt", "s.zarr", "o").engine == "torch"
    with pytest.raises(ValueError, match="engine must be one of"):
        EvaluateConfig("d.pt", "s.pt", "s.zarr", "o", engine="tensorrt")
