"""The runtime as one value: four names, a backend and a precision each, and the former engine/precision pair."""

from __future__ import annotations

import pytest

from models.runtime import RUNTIMES, Runtime
from radar.errors import UserError


def test_every_name_parses_to_its_backend_and_precision_and_back():
    parsed = {name: Runtime.parse(name) for name in RUNTIMES}
    assert {name: (r.backend, r.precision) for name, r in parsed.items()} == {
        "torch": ("torch", "float"), "torch-int8": ("torch", "int8"), "onnx": ("onnx", "float"),
        "onnx-int8": ("onnx", "int8")}
    assert all(r.name == name == str(r) for name, r in parsed.items())
    assert Runtime.parse(parsed["onnx"]) is parsed["onnx"]


@pytest.mark.parametrize("name", ["tensorrt", "int8", "torch-float", "", "ONNX"])
def test_other_names_are_refused_naming_the_four(name):
    with pytest.raises(UserError, match="the runtime is one of torch, torch-int8, onnx, onnx-int8"):
        Runtime.parse(name)


def test_a_runtime_of_unknown_parts_is_refused():
    with pytest.raises(UserError, match="backend is one of torch, onnx"):
        Runtime("tflite")
    with pytest.raises(UserError, match="precision is one of float, int8"):
        Runtime("torch", "fp16")


@pytest.mark.parametrize(("engine", "precision", "name"), [
    ("torch", "float", "torch"), ("torch", "int8", "torch-int8"), ("onnx", "float", "onnx"),
    ("onnx-int8", "float", "onnx-int8"), ("onnx", "int8", "onnx-int8"), ("onnx-int8", "int8", "onnx-int8")])
def test_the_former_pair_names_one_runtime(engine, precision, name):
    assert Runtime.from_engine(engine, precision).name == name


def test_a_former_engine_of_another_name_is_refused_with_the_new_option():
    with pytest.raises(UserError, match="now --runtime"):
        Runtime.from_engine("tensorrt")
