"""The shipped ``carrada`` pair (checkpoints/carrada/) served as users serve it: float and int8, on the viewer's
examples of its radar, finding the example's objects."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from models.export import quantize
from tests.service.conftest import NPY

PAIR = Path(__file__).resolve().parents[2] / "checkpoints" / "carrada"


@pytest.mark.slow  # a paper-size frame per precision, and the int8 calibration at load
def test_the_carrada_pair_serves_its_examples_in_float_and_int8(make_settings, client_for, monkeypatch):
    from service.settings import ModelSpec

    monkeypatch.setattr(quantize, "CALIBRATION_FRAMES", 2)  # calibration frames simulated at load: fewer, faster
    specs = [ModelSpec(name="carrada", detector=PAIR / "detector.pt", segmenter=PAIR / "segmenter.pt"),
             ModelSpec(name="carrada-int8", detector=PAIR / "detector.pt", segmenter=PAIR / "segmenter.pt",
                       runtime="torch-int8")]
    client = client_for(make_settings(models=specs, warmup=False))
    assert client.get("/readyz").status_code == 200, client.get("/readyz").json()
    listing = client.get("/v1/examples", params={"model": "carrada"}).json()
    example = next(e for e in listing["examples"] if e["objects"])
    assert example["preset"] == "carrada" and example["shape"] == [256, 256, 64]
    cube = client.get(example["url"])
    assert cube.status_code == 200 and cube.headers["content-type"] == "application/x-npy"
    truth = np.array([[o["range_m"], o["angle_deg"]] for o in example["objects"]])
    for model in ("carrada", "carrada-int8"):
        answer = client.post("/v1/segment", params={"model": model}, content=cube.content, headers=NPY)
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert body["compute"]["roi_voxels"] > 0 and body["objects"], f"{model}: no object in {example['objects']}"
        misses = [np.min(np.hypot(truth[:, 0] - found["range_m"],
                                  np.radians(truth[:, 1] - found["angle_deg"]) * truth[:, 0]))
                  for found in body["objects"]]
        assert min(misses) < 3.0, (model, body["objects"], example["objects"])  # it finds an object placed there
