"""The Open Inference Protocol (KServe V2) routes against a real ``radarseg serve`` (uvicorn) on loopback, driven by
``tritonclient.http``: health and metadata, the same labels and objects as POST /v1/segment for the same cube (binary
and JSON tensors), the requests billed, and bad input answered in the protocol's error shape, never a 500."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
import tritonclient.http as triton
from tritonclient.utils import InferenceServerException

from service.encoding import decode_array
from tests.service.conftest import NPY, Server, server_env

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def server(tiny_checkpoints, tmp_path_factory):
    root = tmp_path_factory.mktemp("v2")
    api = Server(server_env(tiny_checkpoints, RADARSEG_DATA_DIR=str(root / "data")), root / "server.log")
    try:
        api.wait_ready(timeout_s=400)  # a loaded machine (and a first build of the sparse engine) is slow
        yield api
    finally:
        api.stop()


@pytest.fixture(scope="module")
def client(server):
    with triton.InferenceServerClient(server.url.removeprefix("http://"), network_timeout=120) as c:
        yield c


def _complex_input(cube: np.ndarray, *, binary: bool = True) -> triton.InferInput:
    tensor = np.stack([cube.real, cube.imag], axis=-1).astype(np.float32)  # (R, A, D, 2)
    infer_input = triton.InferInput("complex", list(tensor.shape), "FP32")
    infer_input.set_data_from_numpy(tensor, binary_data=binary)
    return infer_input


def test_health_and_metadata(client, frame):
    assert client.is_server_live() and client.is_server_ready() and client.is_model_ready("tiny")
    assert not client.is_model_ready("missing")
    metadata = client.get_model_metadata("tiny")
    inputs = {i["name"]: (i["shape"], i["parameters"]["datatypes"]) for i in metadata["inputs"]}
    R, A, D = frame.cube.shape
    assert inputs["complex"] == ([R, A, D, 2], "FP32,FP64")
    assert inputs["log_power"] == ([R, A, D], "FP16,FP32,FP64") and set(inputs) == {"complex", "magnitude",
                                                                                    "log_power", "adc"}
    assert [o["name"] for o in metadata["outputs"]] == ["labels", "ra_mask", "rd_mask", "objects", "compute"]
    assert "binary_tensor_data" in client.get_server_metadata()["extensions"]


def _segment_v1(server, cube: np.ndarray, kind: str = "complex") -> dict:
    import io

    buffer = io.BytesIO()
    np.save(buffer, cube)
    answer = httpx.post(f"{server.url}/v1/segment?outputs=objects,masks,voxels&encoding=zlib&input={kind}",
                        content=buffer.getvalue(), headers=NPY, timeout=120)
    assert answer.status_code == 200, answer.text
    return answer.json()


def _check_same_as_v1(result: triton.InferResult, v1: dict) -> None:
    labels = result.as_numpy("labels")
    voxels = decode_array(v1["voxels"]["array"])  # (N, 4): range, angle, Doppler bins and class
    table = np.column_stack([*np.nonzero(labels), labels[np.nonzero(labels)]])
    np.testing.assert_array_equal(np.sort(table, axis=0), np.sort(voxels.astype(np.int64), axis=0))
    np.testing.assert_array_equal(result.as_numpy("ra_mask"), decode_array(v1["ra_mask"]))
    np.testing.assert_array_equal(result.as_numpy("rd_mask"), decode_array(v1["rd_mask"]))
    columns = result.get_output("objects")["parameters"]["columns"].split(",")
    objects = [dict(zip(columns, row, strict=True)) for row in result.as_numpy("objects").tolist()]
    assert [round(o["class_id"]) for o in objects] == [o["class_id"] for o in v1["objects"]]
    for mine, theirs in zip(objects, v1["objects"], strict=True):
        np.testing.assert_allclose([mine[c] for c in ("score", "x", "y")], [theirs[c] for c in ("score", "x", "y")],
                                   rtol=1e-6, atol=1e-6)


def test_binary_infer_answers_what_v1_segment_answers_and_is_billed(client, server, frame):
    v1 = _segment_v1(server, frame.cube)
    outputs = [triton.InferRequestedOutput(name, binary_data=True) for name in
               ("labels", "ra_mask", "rd_mask", "objects", "compute")]
    result = client.infer("tiny", [_complex_input(frame.cube)], outputs=outputs, request_id="r-1")
    _check_same_as_v1(result, v1)
    assert result.get_response()["id"] == "r-1"
    compute = json.loads(result.as_numpy("compute")[0])
    assert compute["compute"]["macs"]["total"] == v1["compute"]["macs"]["total"] > 0
    assert compute["usage"]["requests"] == v1["usage"]["requests"] + 1  # billed as a /v1/segment


def test_json_tensors_and_log_power_input(client, server, frame):
    from radar.transforms import log_power

    cube_db = log_power(frame.cube).astype(np.float32)
    infer_input = triton.InferInput("log_power", list(cube_db.shape), "FP32")
    infer_input.set_data_from_numpy(cube_db, binary_data=False)
    outputs = [triton.InferRequestedOutput(name, binary_data=False) for name in ("labels", "ra_mask", "rd_mask",
                                                                                 "objects")]
    result = client.infer("tiny", [infer_input], outputs=outputs)
    _check_same_as_v1(result, _segment_v1(server, cube_db, "log_power"))
    assert result.as_numpy("compute") is None  # not asked for


def _raw_infer(server, body: bytes, headers: dict[str, str] | None = None, model: str = "tiny") -> httpx.Response:
    return httpx.post(f"{server.url}/v2/models/{model}/infer", content=body, headers=headers or {}, timeout=60)


def _request(name: str, shape: list[int], datatype: str = "FP32", data=None) -> bytes:
    return json.dumps({"inputs": [{"name": name, "shape": shape, "datatype": datatype,
                                   "data": data if data is not None else [0.0]}]}).encode()


def test_bad_input_gets_the_protocol_error_shape_never_a_500(client, server, frame):
    R, A, D = frame.cube.shape
    nan_cube = np.full((R, A, D), 50.0, np.float32)
    nan_cube[0, 0, 0] = np.nan
    header = json.dumps({"inputs": [{"name": "log_power", "shape": [R, A, D], "datatype": "FP32",
                                     "parameters": {"binary_data_size": nan_cube.nbytes}}]}).encode()
    binary = {"Inference-Header-Content-Length": str(len(header))}
    cases = {
        "not json": (_raw_infer(server, b"{nope"), 400, "not a JSON inference request"),
        "wrong shape": (_raw_infer(server, _request("complex", [R, A, D])), 400, "expected [128, 128, 32, 2]"),
        "wrong name": (_raw_infer(server, _request("cube", [R, A, D])), 400, "unknown input 'cube'"),
        "wrong datatype": (_raw_infer(server, _request("log_power", [R, A, D], "INT8")), 400, "datatype 'INT8'"),
        "too few values": (_raw_infer(server, _request("log_power", [R, A, D])), 400, "holds 1 values"),
        "NaN": (_raw_infer(server, header + nan_cube.tobytes(), binary), 422, "NaN"),
        "truncated binary": (_raw_infer(server, header + nan_cube.tobytes()[:100], binary), 400, "binary_data_size"),
        "header length": (_raw_infer(server, header, {"Inference-Header-Content-Length": "x"}), 400,
                          "Inference-Header-Content-Length"),
        "unknown model": (_raw_infer(server, _request("log_power", [R, A, D]), model="nope"), 404, "unknown model"),
    }
    for case, (answer, status, words) in cases.items():
        assert answer.status_code == status, (case, answer.text)
        body = answer.json()
        assert list(body) == ["error"] and words in body["error"], (case, body)
    with pytest.raises(InferenceServerException, match="expected one of"):
        client.infer("tiny", [triton.InferInput("log_power", [R, A, D], "INT8").set_data_from_numpy(
            np.zeros((R, A, D), np.int8))])
    assert httpx.get(f"{server.url}/v2/models/nope", timeout=10).json() == {"error": "unknown model 'nope'; served "
                                                                                     "models: ['tiny']"}
