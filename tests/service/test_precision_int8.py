"""A served model's ``precision``: int8 serves the segmenter in the int8 sparse kernels (calibrated at load), on the
torch engine only (another engine is refused when the settings are read)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from models.export import quantize

NPY = {"content-type": "application/x-npy"}


def test_int8_on_an_onnx_engine_is_refused_in_the_settings(tmp_path):
    from service.settings import ModelSpec

    with pytest.raises(ValidationError, match="precision int8 runs on the torch engine"):
        ModelSpec(name="tiny", detector=tmp_path / "d.pt", segmenter=tmp_path / "s.pt", engine="onnx",
                  precision="int8")
    with pytest.raises(ValidationError):
        ModelSpec(name="tiny", detector=tmp_path / "d.pt", segmenter=tmp_path / "s.pt", precision="int4")


@pytest.mark.slow  # about a minute on our shared 2-core machines (calibration at load, the service's start)
def test_an_int8_model_serves_frames(make_settings, client_for, tiny_checkpoints, cube_body, monkeypatch):
    from service.settings import ModelSpec

    monkeypatch.setattr(quantize, "CALIBRATION_FRAMES", 2)  # calibration frames simulated at load: fewer, faster
    det, seg = tiny_checkpoints
    spec = ModelSpec(name="tiny", detector=det, segmenter=seg, score_threshold=0.0, max_objects=1, precision="int8")
    client = client_for(make_settings(models=[spec]))
    assert client.get("/readyz").status_code == 200, client.get("/readyz").json()
    response = client.post("/v1/segment", content=cube_body, headers=NPY)
    assert response.status_code == 200
    assert response.json()["compute"]["roi_voxels"] > 0
