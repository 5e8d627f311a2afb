"""evaluate takes the runtime it scores as a config field (``--runtime``), checked before anything is loaded; the
former ``--engine`` / ``--precision`` still name one, with a note."""

from __future__ import annotations

import pytest

from pipelines.evaluation import evaluate as evaluate_job
from pipelines.evaluation.evaluate import EvaluateConfig
from pipelines.jobs import parse_config

ARGS = ["--detector", "d.pt", "--segmenter", "s.pt", "--store", "s.zarr", "--out", "o"]


def test_the_runtime_is_a_config_field_and_an_option():
    cfg = parse_config(evaluate_job, [*ARGS, "--runtime", "onnx-int8"], "radarseg evaluate")
    assert cfg.runtime == "onnx-int8" and cfg.onnx_dir is None
    assert EvaluateConfig("d.pt", "s.pt", "s.zarr", "o").runtime == "torch"
    with pytest.raises(ValueError, match="the runtime is one of torch, torch-int8, onnx, onnx-int8, got 'tensorrt'"):
        EvaluateConfig("d.pt", "s.pt", "s.zarr", "o", runtime="tensorrt")


def test_the_former_options_name_a_runtime_with_a_note(capsys):
    cfg = parse_config(evaluate_job, [*ARGS, "--precision", "int8"], "radarseg evaluate")
    assert cfg.runtime == "torch-int8"
    assert "--runtime torch-int8" in capsys.readouterr().err
    cfg = parse_config(evaluate_job, [*ARGS, "--engine", "onnx", "--precision", "int8"], "radarseg evaluate")
    assert cfg.runtime == "onnx-int8"
    with pytest.raises(ValueError, match="disagree"):
        parse_config(evaluate_job, [*ARGS, "--runtime", "torch", "--engine", "onnx"], "radarseg evaluate")
