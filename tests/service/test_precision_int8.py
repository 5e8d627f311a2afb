"""A served model's ``runtime``: torch-int8 serves the segmenter in the int8 sparse kernels (calibrated at load); the
former keys ``engine`` and ``precision`` still name a runtime, and keys that disagree are refused when the settings
are read."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from models.export import quantize

NPY = {"content-type": "application/x-npy"}


def test_the_runtime_and_the_former_keys_in_the_settings(tmp_path, caplog):
    from service.settings import ModelSpec

    pair = {"name": "tiny", "detector": tmp_path / "d.pt", "segmenter": tmp_path / "s.pt"}
    assert ModelSpec(**pair).runtime == "torch"
    assert ModelSpec(**pair, runtime="torch-int8").runtime == "torch-int8"
    assert ModelSpec(**pair, precision="int8").runtime == "torch-int8"
    assert ModelSpec(**pair, engine="onnx", precision="int8").runtime == "onnx-int8"
    assert '"runtime": \'onnx-int8\'' in caplog.text
    with pytest.raises(ValidationError, match="disagree"):
        ModelSpec(**pair, runtime="torch", engine="onnx")
    with pytest.raises(ValidationError):
        ModelSpec(**pair, precision="int4")
    with pytest.raises(ValidationError):
        ModelSpec(**pair, runtime="tensorrt")


@pytest.mark.slow  # about a minute on our shared 2-core machines (calibration at load, the service's start)
def test_an_int8_model_serves_frames(make_settings, client_for, tiny_checkpoints, cube_body, monkeypatch):
    from service.settings import ModelSpec

    monkeypatch.setattr(quantize, "CALIBRATION_FRAMES", 2)  # calibration frames simulated at load: fewer, faster
    det, seg = tiny_checkpoints
    spec = ModelSpec(name="tiny", detector=det, segmenter=seg, score_threshold=0.0, max_objects=1,
                     runtime="torch-int8")
    client = client_for(make_settings(models=[spec]))
    assert client.get("/readyz").status_code == 200, client.get("/readyz").json()
    response = client.post("/v1/segment", content=cube_body, headers=NPY)
    assert response.status_code == 200
    assert response.json()["compute"]["roi_voxels"] > 0
    assert response.json()["compute"]["runtime"] == "torch-int8"
