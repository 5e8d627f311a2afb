"""The HTTP API under the test client: responses, every error code, readiness, saturation, OpenAPI."""

from __future__ import annotations

import json

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from radar import transforms
from service.encoding import decode_array
from tests.service.conftest import NPY, npy_bytes


@pytest.fixture
def client(make_settings, client_for):
    return client_for(make_settings())


def test_segment_returns_objects_masks_voxels_and_compute(client, cube_body, frame):
    r = client.post("/v1/segment?outputs=objects,masks,voxels&encoding=zlib", content=cube_body, headers=NPY)
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["model"] == "tiny" and body["preset"] == "small" and body["shape"] == [128, 128, 32]
    compute = body["compute"]
    macs, seconds = compute["macs"], compute["seconds"]
    assert macs["total"] == macs["detect"] + macs["grow"] + macs["segment"] and macs["segment"] > 0
    assert compute["params"]["total"] == compute["params"]["detector"] + compute["params"]["segmenter"]
    stages = ("decode", "transform", "detect", "grow", "segment", "project")
    assert seconds["total"] == pytest.approx(sum(seconds[s] for s in stages), abs=1e-5)
    assert compute["visited_points"] >= compute["roi_voxels"] > 0
    # the same figures in the headers
    assert int(r.headers["x-compute-macs"]) == macs["total"]
    assert int(r.headers["x-compute-macs-segment"]) == macs["segment"]
    assert float(r.headers["x-compute-seconds"]) == pytest.approx(seconds["total"], abs=1e-6)
    assert int(r.headers["x-roi-voxels"]) == compute["roi_voxels"]
    assert "segment;dur=" in r.headers["server-timing"] and "encode;dur=" in r.headers["server-timing"]
    # masks are the projections of the returned voxels
    ra, rd = decode_array(body["ra_mask"]), decode_array(body["rd_mask"])
    voxels = decode_array(body["voxels"]["array"]).astype(np.int64)
    labels = np.zeros(frame.cube.shape, np.uint8)
    labels[tuple(voxels[:, :3].T)] = voxels[:, 3]
    assert np.array_equal(ra, transforms.project_ra(labels, 4)) and np.array_equal(rd, transforms.project_rd(labels, 4))
    assert body["voxels"]["count"] == len(voxels) == sum(o["n_voxels"] for o in body["objects"])
    assert body["usage"] == {**body["usage"], "tenant": "anonymous", "requests": 1, "macs": macs["total"]}

    # run-length masks decode to the same arrays; log-power input gives the same labels
    rle = client.post("/v1/segment?input=log_power", content=npy_bytes(transforms.log_power(frame.cube)),
                      headers={"content-type": "application/octet-stream"}).json()
    assert rle["ra_mask"]["encoding"] == "rle" and "voxels" not in rle
    assert np.array_equal(decode_array(rle["ra_mask"]), ra) and np.array_equal(decode_array(rle["rd_mask"]), rd)
    assert rle["usage"]["requests"] == 2 and rle["usage"]["macs"] == macs["total"] + rle["compute"]["macs"]["total"]


def _pickled() -> bytes:
    return npy_bytes(np.array([{"a": 1}], dtype=object), allow_pickle=True)


@pytest.mark.parametrize(("case", "status", "message"), [
    ("not_npy", 400, "not a .npy"),
    ("pickled", 400, "refusing .npy with dtype"),
    ("truncated", 400, "needs"),
    ("padded", 400, "needs"),
    ("bad_header", 400, "malformed .npy header"),
    ("wrong_shape", 422, "expects (128, 128, 32)"),
    ("wrong_dtype", 422, "expects a (128, 128, 32) complex64/complex128"),
    ("int_log_power", 422, "float16/float32/float64"),
    ("nan", 422, "NaN or Inf"),
    ("content_type", 415, "application/x-npy"),
    ("unknown_model", 422, "served models: ['tiny']"),
    ("bad_outputs", 422, "unknown outputs"),
    ("bad_input_kind", 422, "input"),
    ("unknown_parameter", 422, "takes encoding, format, frame, input, layout, model, outputs, tdm_compensation"),
    ("float_without_kind", 422, "?input=magnitude or ?input=log_power"),
    ("linear_as_log_power", 422, "linear magnitude or power?"),
    ("log_power_as_magnitude", 422, "looks like log power"),
])
def test_bad_input_gives_its_4xx_and_the_server_stays_up(client, cube_body, frame, case, status, message):
    cube = frame.cube
    url, headers, body = "/v1/segment", NPY, cube_body
    if case == "not_npy":
        body = b"hello world, this is not a cube" * 10
    elif case == "pickled":
        body = _pickled()
    elif case == "truncated":
        body = cube_body[:-100]
    elif case == "padded":
        body = cube_body + b"\0" * 16
    elif case == "bad_header":
        body = cube_body[:10] + b"{'descr': <c8, 'fortran_order'" + cube_body[40:]
    elif case == "wrong_shape":
        body = npy_bytes(cube[:64])
    elif case == "wrong_dtype":
        body = npy_bytes(np.abs(cube).astype(np.float32))
    elif case == "int_log_power":
        url, body = "/v1/segment?input=log_power", npy_bytes(np.zeros(cube.shape, np.int16))
    elif case == "nan":
        bad = cube.copy()
        bad[3, 4, 5] = np.nan
        body = npy_bytes(bad)
    elif case == "content_type":
        headers = {"content-type": "application/json"}
    elif case == "unknown_model":
        url = "/v1/segment?model=huge"
    elif case == "bad_outputs":
        url = "/v1/segment?outputs=objects,everything"
    elif case == "bad_input_kind":
        url = "/v1/segment?input=amplitude"
    elif case == "unknown_parameter":
        url = "/v1/segment?output=objects"
    elif case == "float_without_kind":
        body = npy_bytes(transforms.log_power(cube))
    elif case == "linear_as_log_power":
        url, body = "/v1/segment?input=log_power", npy_bytes(np.abs(cube))
    elif case == "log_power_as_magnitude":
        url, body = "/v1/segment?input=magnitude", npy_bytes(transforms.log_power(cube))
    r = client.post(url, content=body, headers=headers)
    assert r.status_code == status, r.text
    assert message in r.json()["detail"]
    assert r.json()["error"]
    assert client.get("/healthz").status_code == 200
    usage = client.get("/v1/usage").json()["tenants"][0]
    assert usage["today"]["requests"] == 0  # a refused request is not billed


def test_body_over_the_limit_is_413(make_settings, client_for, cube_body):
    limit = len(cube_body) + 1024  # the model's cube fits (a radar whose cube does not is refused at start-up)
    client = client_for(make_settings(max_body_bytes=limit, warmup=False))
    oversized = cube_body + bytes(1 << 16)
    r = client.post("/v1/segment", content=oversized, headers=NPY)
    assert r.status_code == 413
    assert f"{limit} bytes" in r.json()["detail"]

    def chunks():  # no Content-Length: the limit applies to the bytes read
        for start in range(0, len(oversized), 1 << 16):
            yield oversized[start:start + (1 << 16)]

    assert client.post("/v1/segment", content=chunks(), headers=NPY).status_code == 413
    assert client.get("/healthz").status_code == 200


def test_missing_checkpoints_mean_not_ready_but_alive(make_settings, client_for, tmp_path, cube_body):
    from service.settings import ModelSpec

    spec = ModelSpec(name="tiny", detector=tmp_path / "none-det.pt", segmenter=tmp_path / "none-seg.pt")
    client = client_for(make_settings(models=[spec]))
    assert client.get("/healthz").status_code == 200
    ready = client.get("/readyz")
    assert ready.status_code == 503 and "no such checkpoint" in ready.json()["models"]["tiny"]
    r = client.post("/v1/segment", content=cube_body, headers=NPY)
    assert r.status_code == 503 and r.headers["retry-after"] and r.json()["error"] == "not_ready"
    models = client.get("/v1/models").json()["models"]
    assert models[0]["ready"] is False and models[0]["params"] is None


def test_default_settings_point_at_the_shipped_checkpoints():
    from service.settings import REPO_ROOT, Settings, resolve_path

    spec, slimmed = Settings().models
    assert not spec.detector.is_absolute() and not spec.segmenter.is_absolute()
    assert str(spec.detector).startswith("checkpoints/")
    assert resolve_path(spec.detector).parent == REPO_ROOT / "checkpoints"
    assert Settings().default_model_name == "small"  # the slimmed pair is served beside it, not instead of it
    assert slimmed.name == "small-p40" and all(resolve_path(p).is_file() for p in (slimmed.detector, slimmed.segmenter))


def test_the_slimmed_pair_is_smaller_and_serves_the_same_preset():
    from models.checkpoint import load_checkpoint
    from models.compute import count_params
    from service.settings import Settings, resolve_path

    spec, slimmed = Settings().models
    main = [load_checkpoint(resolve_path(p)) for p in (spec.detector, spec.segmenter)]
    slim = [load_checkpoint(resolve_path(p)) for p in (slimmed.detector, slimmed.segmenter)]
    assert [c.preset for c in slim] == [c.preset for c in main] and slim[0].class_names == main[0].class_names
    params = [sum(count_params(c.build()) for c in pair) for pair in (main, slim)]
    assert params[1] <= 0.65 * params[0]  # at least 35 % fewer parameters


def test_saturated_model_answers_503_with_retry_after(make_settings, client_for, cube_body):
    client = client_for(make_settings(max_queue=0, retry_after_s=7))
    served = client.app.state.service.pool.get("tiny")
    served.acquire()  # the one replica is busy
    try:
        r = client.post("/v1/segment", content=cube_body, headers=NPY)
        assert r.status_code == 503 and r.headers["retry-after"] == "7" and r.json()["error"] == "saturated"
    finally:
        served.release()
    assert client.post("/v1/segment", content=cube_body, headers=NPY).status_code == 200
    assert served.held == 0


def test_models_lists_presets_classes_params_and_macs(client):
    body = client.get("/v1/models").json()
    assert body["default"] == "tiny"
    (model,) = body["models"]
    assert model["ready"] and model["preset"] == "small" and model["shape"] == [128, 128, 32]
    assert model["class_names"] == ["background", "pedestrian", "cyclist", "car"]
    assert model["params"]["total"] > 0 and model["detector_macs"] > 0


def test_openapi_describes_every_error(client):
    spec = client.get("/openapi.json").json()
    segment = spec["paths"]["/v1/segment"]["post"]
    assert {"200", "400", "401", "413", "415", "422", "429", "503"} <= set(segment["responses"])
    assert set(segment["requestBody"]["content"]) == {"application/x-npy", "application/octet-stream"}
    assert "403" in spec["paths"]["/v1/usage"]["get"]["responses"]
    assert "503" in spec["paths"]["/readyz"]["get"]["responses"]
    # what the service sends: parameter errors in the ErrorBody shape (the document said otherwise)
    usage_422 = spec["paths"]["/v1/usage"]["get"]["responses"]["422"]["content"]["application/json"]["schema"]
    assert usage_422 == {"$ref": "#/components/schemas/ErrorBody"} and "HTTPValidationError" not in spec["components"]
    assert client.get("/v1/usage?days=0").json()["error"] == "invalid_parameters"
    # the product card's path is the same operation, and every keyed operation documents ambiguous credentials
    alias = spec["paths"]["/segment"]["post"]
    assert alias["responses"].keys() == segment["responses"].keys() and "408" in alias["responses"]
    assert all("400" in op["responses"] for ops in spec["paths"].values() for op in ops.values() if op.get("security"))


def test_metrics_are_exposed_with_bounded_labels(client, cube_body):
    r = client.post("/v1/segment", content=cube_body, headers=NPY)
    macs = r.json()["compute"]["macs"]["total"]
    client.post("/v1/segment", content=b"junk", headers=NPY)
    client.get("/no/such/path/12345")
    text = client.get("/metrics").text
    assert 'radarseg_http_requests_total{method="POST",route="/v1/segment",status="200"} 1.0' in text
    assert 'radarseg_http_errors_total{status="400"} 1.0' in text
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for family in text_string_to_metric_families(text) for s in family.samples}
    assert samples[("radarseg_macs_total", (("model", "tiny"), ("tenant", "anonymous")))] == macs
    assert 'radarseg_segment_requests_total{model="tiny",tenant="anonymous"} 1.0' in text
    assert 'radarseg_stage_duration_seconds_count{model="tiny",stage="segment"} 1.0' in text
    assert 'radarseg_http_request_duration_seconds_bucket' in text
    assert 'route="unmatched"' in text and "12345" not in text
    assert 'radarseg_model_ready{model="tiny"} 1.0' in text


def test_fortran_order_and_big_endian_cubes_give_the_same_answer(client, cube_body, frame):
    reference = client.post("/v1/segment", content=cube_body, headers=NPY).json()
    for variant in (np.asfortranarray(frame.cube), frame.cube.astype(">c8")):
        r = client.post("/v1/segment?outputs=objects,masks", content=npy_bytes(variant), headers=NPY)
        assert r.status_code == 200, r.text
        assert r.json()["ra_mask"] == reference["ra_mask"] and r.json()["objects"] == reference["objects"]
    bad = np.asfortranarray(frame.cube.copy())
    bad[0, 0, 0] = np.inf
    assert client.post("/v1/segment", content=npy_bytes(bad), headers=NPY).status_code == 422


def test_raw_adc_input_gives_the_same_answer_as_its_cube(client, frame):
    """?input=adc: the service runs the ADC -> RAD chain (radar.adc) before the model."""
    adc = frame.extras["adc"]
    by_cube = client.post("/v1/segment", content=npy_bytes(frame.cube), headers=NPY)
    by_adc = client.post("/v1/segment?input=adc", content=npy_bytes(adc), headers=NPY)
    assert by_cube.status_code == by_adc.status_code == 200, by_adc.text
    for mask in ("ra_mask", "rd_mask"):
        assert np.array_equal(decode_array(by_adc.json()[mask]), decode_array(by_cube.json()[mask]))
    wrong = client.post("/v1/segment?input=adc", content=npy_bytes(frame.cube), headers=NPY)
    assert wrong.status_code == 422 and "(samples, chirps, virtual elements)" in wrong.json()["detail"]


def test_a_cube_schema_mismatch_is_a_422_naming_the_difference(client, cube_body):
    import json

    from radar.profiles import CARRADA, SMALL
    from radar.schema import cube_schema

    other = client.post("/v1/segment", content=cube_body,
                        headers={**NPY, "X-Cube-Schema": json.dumps(cube_schema(CARRADA))})
    assert other.status_code == 422
    assert "range.step: expected 0.390625 m, got 0.1953125" in other.json()["detail"]
    same = client.post("/v1/segment", content=cube_body,
                       headers={**NPY, "X-Cube-Schema": json.dumps(cube_schema(SMALL))})
    assert same.status_code == 200
    assert client.post("/v1/segment", content=cube_body, headers={**NPY, "X-Cube-Schema": "{"}).status_code == 400


def test_a_pruned_model_serves_with_its_smaller_compute(make_settings, client_for, tiny_checkpoints, cube_body,
                                                         tmp_path):
    """a checkpoint pruned by `radarseg prune` serves next to its parent; the response's compute
    accounting shows its fewer params and detector MACs (the same cube, so the detector cost is comparable)."""
    from models.checkpoint import load_checkpoint, save_checkpoint
    from models.slimming.prune import prune_checkpoint
    from service.settings import ModelSpec

    det, seg = tiny_checkpoints
    slim = [save_checkpoint(prune_checkpoint(load_checkpoint(path), ratio=0.5)[0], tmp_path / f"slim-{path.name}")
            for path in (det, seg)]
    full_spec = make_settings().models[0]
    slim_spec = ModelSpec(name="tiny-slim", detector=slim[0], segmenter=slim[1], score_threshold=0.0, max_objects=1)
    client = client_for(make_settings(models=[full_spec, slim_spec]))
    full = client.post("/v1/segment?model=tiny", content=cube_body, headers=NPY)
    pruned = client.post("/v1/segment?model=tiny-slim", content=cube_body, headers=NPY)
    assert full.status_code == pruned.status_code == 200, pruned.text
    full_c, slim_c = full.json()["compute"], pruned.json()["compute"]
    assert pruned.json()["model"] == "tiny-slim"
    assert 0 < slim_c["macs"]["detect"] < full_c["macs"]["detect"]
    assert 0 < slim_c["params"]["detector"] < full_c["params"]["detector"]
    assert 0 < slim_c["params"]["segmenter"] < full_c["params"]["segmenter"]
    listed = {m["name"]: m for m in client.get("/v1/models").json()["models"]}
    assert listed["tiny-slim"]["detector_macs"] < listed["tiny"]["detector_macs"]


def test_each_replica_runs_on_its_own_thread_with_the_configured_torch_threads(make_settings, client_for, monkeypatch,
                                                                               cube_body):
    """inference on a pool thread with torch's defaults was 4x slower than in a plain process; each
    replica's inference thread now sets its own torch threads (``torch_threads``, else OMP_NUM_THREADS)."""
    import threading

    import torch

    from service.settings import Settings

    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert Settings().inference_threads == 1 and Settings(torch_threads=3).inference_threads == 3
    client = client_for(make_settings(torch_threads=3, replicas=2))
    served = client.app.state.service.pool.get("tiny")
    seen = {served._executor.submit(lambda: (threading.current_thread().name, torch.get_num_threads())).result()
            for _ in range(4)}
    # One set of inference threads for the whole process, shared by its models.
    assert {threads for _, threads in seen} == {3} and all(name.startswith("inference") for name, _ in seen)
    assert client.post("/v1/segment", content=cube_body, headers=NPY).status_code == 200


def _answers_by_runtime(make_settings, client_for, cube_body, checkpoints, runtimes: dict[str, str]) -> dict:
    """The /v1/segment answer of each served model ``name -> runtime`` (the tiny pair, threshold 0, one object)."""
    from service.settings import ModelSpec

    det, seg = checkpoints
    models = [ModelSpec(name=name, detector=det, segmenter=seg, score_threshold=0.0, max_objects=1, runtime=runtime)
              for name, runtime in runtimes.items()]
    client = client_for(make_settings(models=models))
    bodies = {}
    for name in runtimes:
        r = client.post(f"/v1/segment?model={name}&outputs=objects", content=cube_body, headers=NPY)
        assert r.status_code == 200, r.text
        bodies[name] = r.json()
    return bodies


def test_a_model_served_by_the_onnx_engine_answers_like_the_torch_one(make_settings, client_for, cube_body,
                                                                      tiny_checkpoints, monkeypatch, tmp_path):
    monkeypatch.setenv("RADARSEG_ONNX_CACHE", str(tmp_path / "onnx"))
    bodies = _answers_by_runtime(make_settings, client_for, cube_body, tiny_checkpoints,
                                {"tiny": "torch", "tiny-onnx": "onnx"})
    assert bodies["tiny"]["compute"]["runtime"] == "torch" and bodies["tiny-onnx"]["compute"]["runtime"] == "onnx"
    assert all(body["compute"]["engine"] == body["compute"]["runtime"] for body in bodies.values())  # former name
    assert bodies["tiny-onnx"]["compute"]["macs"] == bodies["tiny"]["compute"]["macs"]
    classes = {name: [o["class_name"] for o in body["objects"]] for name, body in bodies.items()}
    assert classes["tiny-onnx"] == classes["tiny"]


def test_a_model_served_by_the_int8_onnx_engine_names_its_precision(make_settings, client_for, cube_body,
                                                                    tiny_checkpoints, monkeypatch, tmp_path):
    """onnx-int8 needs no store: the service's model calibrates on simulated frames of its preset."""
    monkeypatch.setenv("RADARSEG_ONNX_CACHE", str(tmp_path / "onnx"))
    monkeypatch.setattr("models.export.quantize.CALIBRATION_FRAMES", 2)  # a quick calibration for the test
    monkeypatch.setattr("models.export.quantize.METHODS", ("MinMax",))
    bodies = _answers_by_runtime(make_settings, client_for, cube_body, tiny_checkpoints,
                                {"tiny-onnx": "onnx", "tiny-int8": "onnx-int8"})
    assert bodies["tiny-int8"]["compute"]["runtime"] == "onnx-int8"
    assert bodies["tiny-onnx"]["compute"]["runtime"] == "onnx"
    manifests = [json.loads(p.read_text()) for p in (tmp_path / "onnx").glob("*/manifest.json")]
    int8 = [m for m in manifests if m.get("precision") == "int8"]
    assert len(int8) == 1 and int8[0]["quantization"]["calibration"]["source"] == "simulated"
    assert len(bodies["tiny-int8"]["objects"]) == len(bodies["tiny-onnx"]["objects"])
