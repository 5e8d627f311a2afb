"""GET /v1/examples and /v1/examples/{n}: simulated cubes for the model's preset, from fixed seeds."""

from __future__ import annotations

import io

import numpy as np

from radar.simulate import simulate_sequence
from service.routes.examples import EXAMPLE_SEEDS, MIN_VOXELS
from tests.service.conftest import KEYS, NPY


def test_examples_are_the_simulators_frames_for_the_fixed_seeds_and_segment(make_settings, client_for):
    client = client_for(make_settings())
    listing = client.get("/v1/examples")
    assert listing.status_code == 200, listing.text
    examples = listing.json()["examples"]
    assert listing.json()["model"] == "tiny" and [e["n"] for e in examples] == [1, 2, 3]
    assert [e["seed"] for e in examples] == list(EXAMPLE_SEEDS)
    first = examples[0]
    truth = next(simulate_sequence("small", 1, seed=first["seed"]))
    assert first["shape"] == [128, 128, 32] and first["preset"] == "small" and first["dtype"] == "complex64"
    assert [o["class_name"] for o in first["objects"]] == [o.class_name for o in truth.objects
                                                         if o.n_voxels >= MIN_VOXELS]
    assert {o["class_name"] for e in examples for o in e["objects"]} == {"pedestrian", "cyclist", "car"}

    r = client.get(first["url"])
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-npy"
    assert r.headers["x-example-seed"] == str(first["seed"])
    assert "example-1-small.npy" in r.headers["content-disposition"]
    cube = np.load(io.BytesIO(r.content), allow_pickle=False)
    np.testing.assert_array_equal(cube, truth.cube)
    segmented = client.post("/v1/segment", content=r.content, headers=NPY)
    assert segmented.status_code == 200, segmented.text


def test_example_errors_are_json_4xx(make_settings, client_for):
    client = client_for(make_settings())
    for path, status, words in (("/v1/examples/0", 404, "numbered 1 to 3"), ("/v1/examples/4", 404, "no example 4"),
                                ("/v1/examples/one", 422, "integer"), ("/v1/examples?model=nope", 422, "tiny"),
                                ("/v1/examples/1?model=nope", 422, "unknown model")):
        r = client.get(path)
        assert r.status_code == status and words in r.json()["detail"], (path, r.text)


def test_examples_need_a_key_when_keys_are_configured(make_settings, client_for):
    client = client_for(make_settings(api_keys=KEYS))
    assert client.get("/v1/examples").status_code == 401
    assert client.get("/v1/examples/1").json()["error"] == "unauthorized"
    key = {"X-API-Key": next(iter(KEYS))}
    assert client.get("/v1/examples", headers=key).status_code == 200
    assert client.get("/v1/examples/2", headers=key).status_code == 200


def test_examples_are_documented(make_settings, client_for):
    paths = client_for(make_settings()).get("/openapi.json").json()["paths"]
    assert "application/x-npy" in paths["/v1/examples/{n}"]["get"]["responses"]["200"]["content"]
    assert {"200", "404", "401"} <= set(paths["/v1/examples/{n}"]["get"]["responses"])
    assert "ExamplesResponse" in paths["/v1/examples"]["get"]["responses"]["200"]["content"]["application/json"][
        "schema"]["$ref"]
