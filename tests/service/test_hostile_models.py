"""Models the service must refuse at start-up, with one line, instead of failing every request: a radar whose
``[tracking]`` table cannot build a tracker (every stream frame was billed and answered 500), a radar whose cube
does not fit the body limit, and a radar too large to allocate. ``/v1/models`` shows tenants no absolute paths."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest

from models.checkpoint import load_checkpoint, save_checkpoint
from service.http.public_text import printable, without_directories
from service.settings import ModelSpec
from tests.service.conftest import KEYS

SMALL = tomllib.loads((Path(__file__).resolve().parents[2] / "radar/profiles/presets/small.toml").read_text())


def _with_radar(checkpoints, tmp_path: Path, name: str, **tables) -> tuple[Path, Path]:
    """The tiny pair re-saved for a radar described by a file: the small preset's with ``tables`` merged in."""
    radar = copy.deepcopy(SMALL)
    radar["name"] = name
    for table, values in tables.items():
        radar.setdefault(table, {}).update(values)
    if "processing" in tables:
        radar.pop("expect", None)
    out = []
    for path in checkpoints:
        checkpoint = load_checkpoint(path)
        checkpoint.preset = checkpoint.config["preset"] = name
        checkpoint.extra["radar_file"] = radar
        out.append(save_checkpoint(checkpoint, tmp_path / f"{name}-{Path(path).name}"))
    return out[0], out[1]


@pytest.mark.parametrize(("tables", "words"), [
    ({"tracking": {"confirm_hits": 0}}, "confirm_hits"),
    ({"tracking": {"max_misses": 10**9}}, "max_misses = 1000000000"),
    ({"processing": {"angle_bins": 65536}}, "angle_bins = 65536"),
])
def test_a_model_whose_radar_is_out_of_bounds_is_refused_at_start_up(
        make_settings, client_for, tiny_checkpoints, tmp_path, tables, words):
    det, seg = _with_radar(tiny_checkpoints, tmp_path, "lab", **tables)
    client = client_for(make_settings(models=[ModelSpec(name="tiny", detector=det, segmenter=seg)], warmup=False))
    ready = client.get("/readyz")
    assert ready.status_code == 503 and words in ready.json()["models"]["tiny"], ready.text
    assert str(tmp_path) not in ready.text  # the public probe names files, not the host's directories
    frame = client.post("/v1/segment", content=b"x", headers={"content-type": "application/x-npy"})
    assert frame.status_code == 503 and frame.json()["error"] == "not_ready"
    assert client.post("/v1/streams").status_code in (201, 503)


def test_a_radar_whose_cube_does_not_fit_the_body_limit_is_refused_at_start_up(make_settings, client_for):
    client = client_for(make_settings(max_body_bytes=2**20, warmup=False))  # the small cube is 4 MiB
    ready = client.get("/readyz").json()
    assert "max_body_bytes" in ready["models"]["tiny"] and "(128, 128, 32)" in ready["models"]["tiny"], ready


def test_models_show_tenants_file_names_and_admins_the_paths(make_settings, client_for, tiny_checkpoints):
    client = client_for(make_settings(api_keys=KEYS, admin_tenants=["ops"], warmup=False))
    keys = {tenant: {"X-API-Key": key} for key, tenant in KEYS.items()}
    tenant = client.get("/v1/models", headers=keys["acme"]).json()["models"][0]
    assert tenant["detector_checkpoint"] == Path(tiny_checkpoints[0]).name
    admin = client.get("/v1/models", headers=keys["ops"]).json()["models"][0]
    assert admin["detector_checkpoint"] == str(tiny_checkpoints[0])


def test_names_are_printable_in_logs_and_paths_lose_their_directories():
    assert printable("radar\r\nINFO forged line\x1b[2J") == "radar\\r\\nINFO forged line\\x1b[2J"
    missing = "/srv/a/b/detector.pt: no such checkpoint file"
    assert without_directories(missing) == "detector.pt: no such checkpoint file"
    assert without_directories("checkpoints/detector.pt") == "checkpoints/detector.pt"
