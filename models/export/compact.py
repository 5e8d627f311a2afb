"""Smaller ONNX files for the edge, without changing what a graph computes:

- :func:`int8_weights`: the weights of the convolutions and matrix products stored as int8 (symmetric, one scale per
  output channel) behind a DequantizeLinear, activations untouched. onnxruntime folds those DequantizeLinear nodes
  back into float weights when the session is built with ``session.disable_quant_qdq`` (:data:`FOLD_WEIGHTS`), so
  the graph runs at its float speed from a quarter of the weight bytes; for a graph whose int8 compute is slower
  than float (the detector, see :mod:`models.export.quantize`).
- :func:`short_names`: every internal tensor renamed ``t<hex>``, node names, doc strings and shape annotations
  dropped (inputs and outputs keep their names): most of a quantised sparse graph's bytes are the names of its
  thousands of nodes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

WEIGHT_OPS = ("Conv", "ConvTranspose", "Gemm", "MatMul")
MIN_WEIGHT_ELEMENTS = 64  # smaller weights are not worth a scale per channel
FOLD_WEIGHTS = ("session.disable_quant_qdq", "1")
"""The onnxruntime session option under which a graph from :func:`int8_weights` runs on folded float weights (without
it, the runtime keeps the DequantizeLinear nodes for QDQ fusion and runs them every call: 1.7x the float time)."""


def int8_weights(source: str | Path, target: str | Path) -> int:
    """Write ``source`` with int8 weights into ``target``; the number of weights converted."""
    import onnx
    from onnx import helper, numpy_helper

    model = onnx.load(str(source))
    graph = model.graph
    weights = {node.input[1] for node in graph.node if node.op_type in WEIGHT_OPS and len(node.input) > 1}
    initializers, dequantize = [], []
    for tensor in graph.initializer:
        value = numpy_helper.to_array(tensor)
        small = value.ndim < 2 or value.size < MIN_WEIGHT_ELEMENTS
        if tensor.name not in weights or value.dtype != np.float32 or small:
            initializers.append(tensor)
            continue
        axis = 1 if _is_matmul_weight(graph, tensor.name) else 0  # the output channel
        peak = np.abs(np.moveaxis(value, axis, 0).reshape(value.shape[axis], -1)).max(axis=1)
        scale = np.where(peak > 0, peak / 127.0, 1.0).astype(np.float32)
        shape = [1] * value.ndim
        shape[axis] = -1
        quantised = np.clip(np.round(value / scale.reshape(shape)), -127, 127).astype(np.int8)
        names = (f"{tensor.name}__int8", f"{tensor.name}__scale", f"{tensor.name}__zero")
        initializers += [numpy_helper.from_array(quantised, names[0]), numpy_helper.from_array(scale, names[1]),
                         numpy_helper.from_array(np.zeros(scale.shape, np.int8), names[2])]
        dequantize.append(helper.make_node("DequantizeLinear", list(names), [tensor.name], axis=axis))
    del graph.initializer[:]
    graph.initializer.extend(initializers)
    nodes = list(graph.node)
    del graph.node[:]
    graph.node.extend(dequantize + nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(target))
    return len(dequantize)


def _is_matmul_weight(graph, name: str) -> bool:  # noqa: ANN001
    """A MatMul's (C_in, C_out) weight has its output channel on axis 1 (a Conv's on axis 0)."""
    return any(node.op_type in ("MatMul", "Gemm") and node.input[1] == name for node in graph.node)


def short_names(source: str | Path, target: str | Path) -> None:
    """Write ``source`` with short internal names into ``target`` (same computation, same inputs and outputs)."""
    import onnx

    model = onnx.load(str(source))
    graph = model.graph
    keep = {value.name for value in list(graph.input) + list(graph.output)}
    renamed: dict[str, str] = {}

    def short(name: str) -> str:
        if not name or name in keep:
            return name
        return renamed.setdefault(name, f"t{len(renamed):x}")

    for node in graph.node:
        node.name = ""
        node.doc_string = ""
        node.input[:] = [short(name) for name in node.input]
        node.output[:] = [short(name) for name in node.output]
    for tensor in graph.initializer:
        tensor.name = short(tensor.name)
    del graph.value_info[:]
    model.doc_string = graph.doc_string = ""
    onnx.checker.check_model(model)
    onnx.save(model, str(target))
