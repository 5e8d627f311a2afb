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
                                                                                    "log_power", "adc", "adc_iq"}
    iq = next(i for i in metadata["inputs"] if i["name"] == "adc_iq")  # int16 I/Q, as a TI radar gives them
    S, C, V = frame.extras["adc"].shape
    assert (iq["datatype"], iq["shape"], iq["parameters"]["datatypes"]) == ("INT16", [S, C, V, 2], "INT16")
    assert iq["parameters"]["shapes"].startswith(f"[{S}, {C}, {V}, 2] sck") and " ti (chirps, rx, samples)" in \
        iq["parameters"]["shapes"]
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


def _int16_iq(adc: np.ndarray) -> np.ndarray:
    """Complex ADC samples at a 16-bit ADC's scale, as int16 with I and Q on a trailing axis of 2."""
    decoded = np.round(adc / np.abs(adc).std() * 200)
    return np.stack([decoded.real, decoded.imag], axis=-1).astype(np.int16)


def _iq_input(iq: np.ndarray, datatype: str = "INT16") -> triton.InferInput:
    infer_input = triton.InferInput("adc_iq", list(iq.shape), datatype)
    infer_input.set_data_from_numpy(iq)
    return infer_input


@pytest.fixture(scope="module")
def openradar_server(tmp_path_factory):
    """The service with a model of the TI radar that recorded OpenRadar's frame (the tiny model of the simulated
    radar finds nothing in ADC frames: a comparison of empty answers would not tell layouts apart)."""
    from tests.service.openradar_model import save_openradar_checkpoints

    root = tmp_path_factory.mktemp("v2-openradar")
    det, seg = save_openradar_checkpoints(root)
    models = [{"name": "openradar", "detector": str(det), "segmenter": str(seg), "score_threshold": 0.0,
               "max_objects": 1}]
    api = Server({"RADARSEG_MODELS": json.dumps(models), "RADARSEG_DATA_DIR": str(root / "data")},
                 root / "server.log")
    try:
        api.wait_ready(timeout_s=400)
        yield api
    finally:
        api.stop()


def test_int16_iq_in_either_layout_answers_what_v1_segment_answers(openradar_server):
    from tests.service.openradar_model import sck_frame, ti_frame_iq

    ti_iq = ti_frame_iq()  # (chirps, rx, samples, 2) int16, as the radar recorded it
    sck_iq = np.stack([sck_frame().real, sck_frame().imag], axis=-1).astype(np.int16)  # (samples, chirps, virtual, 2)
    v1 = _segment_v1(openradar_server, ti_iq, "adc")
    assert v1["objects"] and decode_array(v1["voxels"]["array"]).size, "an empty answer tells no layouts apart"
    host = openradar_server.url.removeprefix("http://")
    with triton.InferenceServerClient(host, network_timeout=120) as client:
        iq = next(i for i in client.get_model_metadata("openradar")["inputs"] if i["name"] == "adc_iq")
        assert (iq["datatype"], iq["shape"]) == ("INT16", list(sck_iq.shape)), iq
        assert str(list(ti_iq.shape)) in iq["parameters"]["shapes"]
        for what, tensor in {"ti": ti_iq, "sck": sck_iq}.items():
            result = client.infer("openradar", [_iq_input(tensor)], outputs=[
                triton.InferRequestedOutput(name) for name in ("labels", "ra_mask", "rd_mask", "objects", "compute")])
            _check_same_as_v1(result, v1)
            compute = json.loads(result.as_numpy("compute")[0])
            assert compute["compute"]["macs"]["total"] == v1["compute"]["macs"]["total"], what


def _binary_body(name: str, array: np.ndarray, datatype: str) -> tuple[bytes, dict[str, str]]:
    header = json.dumps({"inputs": [{"name": name, "shape": list(array.shape), "datatype": datatype,
                                     "parameters": {"binary_data_size": array.nbytes}}]}).encode()
    return header + array.tobytes(), {"Inference-Header-Content-Length": str(len(header))}


def test_int16_iq_that_does_not_fit_is_refused_with_what_was_expected(client, server, frame):
    iq = _int16_iq(frame.extras["adc"])
    S, C, V, _ = iq.shape
    sck = f"[{S}, {C}, {V}, 2]"
    words = iq.view(np.uint16)  # two's-complement samples read as unsigned words: undecoded
    whole = _binary_body("adc_iq", iq, "INT16")
    cases = {
        "no I/Q axis": (_binary_body("adc_iq", iq[..., 0].copy(), "INT16"), 400, "trailing axis of 2 is missing"),
        "wrong shape": (_binary_body("adc_iq", iq[:, :, :1].copy(), "INT16"), 400, f"expected {sck} or ["),
        "three parts": (_binary_body("adc_iq", np.zeros((S, C, V, 3), np.int16), "INT16"), 400, f"expected {sck}"),
        "FP32 pairs": (_binary_body("adc_iq", iq.astype(np.float32), "FP32"), 400, "datatype 'FP32', expected one "
                                                                                   "of ['INT16'"),
        "int16 as adc": (_binary_body("adc", iq, "INT16"), 400, "datatype 'INT16', expected one of ['FP32'"),
        "undecoded words": (_binary_body("adc_iq", words, "UINT16"), 422, "((x + 32768) % 65536) - 32768"),
        "nothing but DC": (_binary_body("adc_iq", np.full(iq.shape, 100, np.int16), "INT16"), 422, "offset"),
        "too short": ((whole[0][:-2], whole[1]), 400, "binary_data_size"),
    }
    for case, ((body, headers), status, expected) in cases.items():
        answer = _raw_infer(server, body, headers)
        assert answer.status_code == status, (case, answer.text)
        assert list(answer.json()) == ["error"] and expected in answer.json()["error"], (case, answer.json())
    json_overflow = _request("adc_iq", [S, C, V, 2], "INT16", [40000] * (S * C * V * 2))
    answer = _raw_infer(server, json_overflow)
    assert answer.status_code == 400 and "is not int16: integers in" in answer.json()["error"], answer.text
    with pytest.raises(InferenceServerException, match="raw unsigned 16-bit words"):
        client.infer("tiny", [_iq_input(words, "UINT16")])


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
