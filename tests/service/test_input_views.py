"""POST /v1/segment?outputs=views: the RA/RD views of the input, as the viewer draws them."""

from __future__ import annotations

import numpy as np

from radar import transforms
from radar.input_kind import InputKind
from radar.profiles import get_profile
from service.encoding import decode_array
from tests.service.conftest import NPY, npy_bytes


def _db(view: dict) -> np.ndarray:
    levels = decode_array(view["array"]).astype(np.float64)
    return view["low_db"] + levels * (view["high_db"] - view["low_db"]) / 255.0


def test_views_are_the_inputs_ra_and_rd_views_within_one_quantization_step(make_settings, client_for, frame):
    client = client_for(make_settings())
    log_power = transforms.log_power(frame.cube)
    expected = {"ra": transforms.ra_view(log_power, kind=InputKind.log_power),
                "rd": transforms.rd_view(log_power, kind=InputKind.log_power)}
    for body, query in ((npy_bytes(frame.cube), ""), (npy_bytes(log_power), "&input=log_power")):
        for encoding in ("zlib", "rle"):
            r = client.post(f"/v1/segment?outputs=views&encoding={encoding}{query}", content=body, headers=NPY)
            assert r.status_code == 200, r.text
            answer = r.json()
            assert "objects" not in answer and "ra_mask" not in answer  # only what was asked for
            views = answer["views"]
            for name, truth in expected.items():
                assert views[name]["array"]["dtype"] == "uint8" and views[name]["array"]["shape"] == list(truth.shape)
                step = (views[name]["high_db"] - views[name]["low_db"]) / 255.0
                assert np.abs(_db(views[name]) - truth).max() <= 0.5 * step + 1e-3
                assert views[name]["low_db"] == round(float(truth.min()), 3)


def test_view_axes_give_metres_degrees_and_metres_per_second_per_bin(make_settings, client_for, cube_body):
    r = client_for(make_settings()).post("/v1/segment?outputs=objects,masks,views", content=cube_body, headers=NPY)
    assert r.status_code == 200, r.text
    axes, profile = r.json()["views"]["axes"], get_profile("small")
    n_range, n_angle, n_doppler = profile.shape
    assert len(axes["range_m"]) == n_range and axes["range_m"][1] == round(profile.range_res, 4)
    assert len(axes["angle_deg"]) == n_angle and axes["angle_deg"][n_angle // 2] == 0.0
    assert axes["angle_deg"][0] == -90.0 and np.all(np.diff(axes["angle_deg"]) > 0)
    assert len(axes["velocity_mps"]) == n_doppler and axes["velocity_mps"][n_doppler // 2] == 0.0
    assert "ra_mask" in r.json() and "objects" in r.json()


def test_views_option_is_documented_and_an_unknown_output_is_a_422(make_settings, client_for, cube_body):
    client = client_for(make_settings())
    schema = client.get("/openapi.json").json()
    assert "InputViews" in schema["components"]["schemas"]
    params = {p["name"]: p for p in schema["paths"]["/v1/segment"]["post"]["parameters"]}
    assert "views" in params["outputs"]["description"]
    r = client.post("/v1/segment?outputs=view", content=cube_body, headers=NPY)
    assert r.status_code == 422 and "views" in r.json()["detail"]


def test_adc_views_come_from_the_one_processed_cube_inside_the_billed_compute(make_settings, client_for, frame,
                                                                             monkeypatch):
    """?input=adc&outputs=views: the ADC -> RAD chain runs once per request (the model's), the views are the
    processed cube's, and their time is inside the compute the answer reports."""
    import service.inference

    calls = []
    real = service.inference.process_adc
    monkeypatch.setattr(service.inference, "process_adc", lambda *a, **k: calls.append(1) or real(*a, **k))
    client = client_for(make_settings())
    by_cube = client.post("/v1/segment?outputs=views", content=npy_bytes(frame.cube), headers=NPY)
    by_adc = client.post("/v1/segment?input=adc&outputs=views", content=npy_bytes(frame.extras["adc"]), headers=NPY)
    assert by_cube.status_code == by_adc.status_code == 200, by_adc.text
    assert len(calls) == 1
    for name in ("ra", "rd"):
        assert np.abs(_db(by_adc.json()["views"][name]) - _db(by_cube.json()["views"][name])).max() < 0.5
    seconds = by_adc.json()["compute"]["seconds"]
    assert seconds["project"] > 0 and seconds["total"] >= seconds["transform"] + seconds["project"]
