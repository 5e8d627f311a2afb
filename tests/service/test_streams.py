"""Streams (service.routes.streams, service.streams.store): order, gaps, tenancy, expiry, the per-tenant cap, one frame
at a time, billing per frame, and a replica restarted mid-stream that continues every track."""

from __future__ import annotations

import datetime as dt
import time

import numpy as np
import pytest

from radar.simulate import simulate_sequence
from service.accounting.ledger import Ledger
from service.settings import ModelSpec
from service.streams.store import Refusal, StreamStore
from tests.service.conftest import KEYS, NPY, npy_bytes

AUTH = {tenant: {"authorization": f"Bearer {key}"} for key, tenant in KEYS.items()}
SHIPPED = ModelSpec(name="small", detector="checkpoints/detector.pt", segmenter="checkpoints/segmenter.pt")


@pytest.fixture(scope="module")
def sequence() -> list[np.ndarray]:
    """Six consecutive frames of one simulated sequence (cubes)."""
    return [frame.cube for frame in simulate_sequence("small", 6, seed=31)]


def _frame(client, stream_id: str, seq: int, cube: np.ndarray, headers: dict | None = None):
    return client.post(f"/v1/streams/{stream_id}/frames?seq={seq}", content=npy_bytes(cube),
                       headers={**NPY, **(headers or {})})


def test_order_gap_and_billing(make_settings, client_for, sequence):
    client = client_for(make_settings())
    created = client.post("/v1/streams")
    assert created.status_code == 201, created.text
    stream_id = created.json()["id"]
    assert created.json()["last_seq"] is None and created.json()["tracks"] == []
    first = _frame(client, stream_id, 0, sequence[0])
    assert first.status_code == 200, first.text
    body = first.json()
    assert body["seq"] == 0 and body["stream"]["frames"] == 1 and body["stream"]["last_seq"] == 0
    assert all({"track_id", "vx", "vy"} <= set(obj) for obj in body["objects"])
    assert body["usage"]["requests"] == 1  # billed as a /v1/segment request

    for seq in (0, -1):
        refused = _frame(client, stream_id, seq, sequence[1])
        assert refused.status_code in (409, 422)
    assert _frame(client, stream_id, 0, sequence[1]).json()["error"] == "stream_order"
    # a gap of two frames is coasted: the frame is taken and the stream's last frame is 3
    gap = _frame(client, stream_id, 3, sequence[3])
    assert gap.status_code == 200 and gap.json()["stream"]["last_seq"] == 3 and gap.json()["stream"]["frames"] == 2
    assert gap.json()["usage"]["requests"] == 2  # the refused frames were not billed
    shown = client.get(f"/v1/streams/{stream_id}")
    assert shown.status_code == 200 and shown.json()["last_seq"] == 3

    assert client.delete(f"/v1/streams/{stream_id}").status_code == 204
    assert client.get(f"/v1/streams/{stream_id}").status_code == 404
    assert _frame(client, stream_id, 4, sequence[4]).status_code == 404
    assert client.delete(f"/v1/streams/{stream_id}").status_code == 404


def test_streams_belong_to_their_tenant_and_are_capped(make_settings, client_for, sequence):
    client = client_for(make_settings(api_keys=dict(KEYS), max_streams_per_tenant=2))
    acme, globex = AUTH["acme"], AUTH["globex"]
    stream_id = client.post("/v1/streams", headers=acme).json()["id"]
    assert client.get(f"/v1/streams/{stream_id}", headers=globex).status_code == 404
    assert _frame(client, stream_id, 0, sequence[0], globex).status_code == 404
    assert client.delete(f"/v1/streams/{stream_id}", headers=globex).status_code == 404
    assert client.get(f"/v1/streams/{stream_id}", headers=acme).status_code == 200
    assert client.post("/v1/streams").status_code == 401

    assert client.post("/v1/streams", headers=acme).status_code == 201
    capped = client.post("/v1/streams", headers=acme)
    assert capped.status_code == 429 and capped.json()["error"] == "too_many_streams"
    assert client.post("/v1/streams", headers=globex).status_code == 201  # another tenant's cap is its own
    assert client.delete(f"/v1/streams/{stream_id}", headers=acme).status_code == 204
    assert client.post("/v1/streams", headers=acme).status_code == 201


def test_bad_requests_are_refused_with_what_was_expected(make_settings, client_for, sequence):
    client = client_for(make_settings())
    assert client.post("/v1/streams", json={"model": "nope"}).status_code == 422
    assert client.post("/v1/streams", json={"model": "tiny", "extra": 1}).status_code == 422
    assert client.get("/v1/streams/not-an-id").status_code == 422
    stream_id = client.post("/v1/streams", json={"model": "tiny"}).json()["id"]
    missing_seq = client.post(f"/v1/streams/{stream_id}/frames", content=npy_bytes(sequence[0]), headers=NPY)
    assert missing_seq.status_code == 422
    wrong_shape = _frame(client, stream_id, 0, sequence[0][:64])
    assert wrong_shape.status_code == 422 and "expects" in wrong_shape.json()["detail"]
    assert client.get(f"/v1/streams/{stream_id}").json()["frames"] == 0  # a refused frame changes nothing
    assert _frame(client, stream_id, 0, sequence[0]).status_code == 200


def test_idle_streams_expire(make_settings, client_for, sequence):
    client = client_for(make_settings(stream_idle_s=1))
    stream_id = client.post("/v1/streams").json()["id"]
    assert _frame(client, stream_id, 0, sequence[0]).status_code == 200
    time.sleep(1.3)
    expired = client.get(f"/v1/streams/{stream_id}")
    assert expired.status_code == 404 and expired.json()["error"] == "stream_expired"
    assert _frame(client, stream_id, 1, sequence[1]).status_code == 404


def _store(url: str, prefix: str = "radarseg_", **kwargs) -> StreamStore:
    ledger = Ledger(url, table_prefix=prefix, pool_size=0 if url.startswith("postgresql") else 8)
    store = StreamStore(ledger, **{"idle_s": 60, "claim_s": 30, "max_per_tenant": 4, **kwargs})
    ledger.create()
    return store


def _claim_story(store: StreamStore) -> dict[str, object]:
    """What the store answers along one stream's life: two frames at once, another tenant, an older frame, a gap, a
    failed frame, and a claim left by a replica that died mid-frame (free once it runs out; its frame writes
    nothing)."""
    stream = store.create("acme", "tiny")
    first = store.claim("acme", stream.id, 0)
    story: dict[str, object] = {"first": type(first).__name__,
                                "while_first_runs": store.claim("acme", stream.id, 1),
                                "other_tenant": store.claim("globex", stream.id, 1),
                                "first_written": store.commit(first, {"version": 1, "tracks": []}),
                                "older_frame": store.claim("acme", stream.id, 0)}
    second = store.claim("acme", stream.id, 2)
    story["gap"] = second.gap
    store.release(second)  # a failed frame writes nothing
    story["last_seq_after_failure"] = store.get("acme", stream.id).last_seq
    later = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=31)
    dead = store.claim("acme", stream.id, 1)
    taken = store.claim("acme", stream.id, 1, now=later)
    story["dead_frame_written"] = store.commit(dead, {"stale": True})
    story["taken_frame_written"] = store.commit(taken, {"version": 1, "tracks": []})
    story["frames"] = store.get("acme", stream.id, now=later).frames
    return story


CLAIM_STORY = {"first": "Claim", "while_first_runs": Refusal.busy, "other_tenant": Refusal.missing,
               "first_written": None, "older_frame": Refusal.stale, "gap": 2, "last_seq_after_failure": 0,
               "dead_frame_written": Refusal.lost, "taken_frame_written": None, "frames": 2}


def test_store_sqlite(tmp_path):
    assert _claim_story(_store(f"sqlite:///{tmp_path / 'ledger.sqlite3'}")) == CLAIM_STORY


def test_store_postgres(postgres_url, pg_prefix):
    assert _claim_story(_store(postgres_url, pg_prefix)) == CLAIM_STORY


@pytest.mark.slow
def test_a_replica_restarted_mid_stream_loses_no_track(make_settings, client_for, sequence, tmp_path):
    """The shipped pair on one sequence: a stream whose replica restarts after frame 2 answers frames 3-5 exactly
    as a stream that ran through, and keeps every confirmed track. The shipped detector reads the frame before,
    which lives in the replica's memory only (a restarted replica would run frame 3 alone): with no earlier frames
    kept (``stream_history_bytes=0``) both streams run every frame alone, so what this compares is the ledger's
    track state."""
    from fastapi.testclient import TestClient

    from service.main import create_app

    settings = make_settings(models=[SHIPPED], data_dir=tmp_path / "restart", stream_history_bytes=0)
    with TestClient(create_app(settings)) as first:
        through = first.post("/v1/streams").json()["id"]
        reference = [_frame(first, through, seq, cube).json() for seq, cube in enumerate(sequence)]
        interrupted = first.post("/v1/streams").json()["id"]
        answers = [_frame(first, interrupted, seq, sequence[seq]).json() for seq in range(3)]
        before = first.get(f"/v1/streams/{interrupted}").json()
    assert before["tracks"], "the shipped pair confirms at least one track in three frames"

    second = client_for(settings)  # a new app (as a restarted process) on the same ledger
    assert second.get(f"/v1/streams/{interrupted}").json()["tracks"] == before["tracks"]
    answers += [_frame(second, interrupted, seq, sequence[seq]).json() for seq in range(3, 6)]

    def tracked(frames: list) -> list:
        return [(o["track_id"], o["class_name"], o["vx"], o["vy"]) for a in frames for o in a["objects"]]

    assert tracked(answers) == tracked(reference)
    assert answers[-1]["stream"]["tracks"] == reference[-1]["stream"]["tracks"]
    after_ids = {o["track_id"] for o in answers[3]["objects"]}
    assert {t["track_id"] for t in before["tracks"]} & after_ids, "frame 3 continues tracks confirmed before"


def test_a_stream_seeds_from_its_tracks_when_the_service_is_told_to(make_settings, client_for):
    """RADARSEG_STREAM_TRACK_PRIORS: from the third frame on (tracks confirmed) the stream's tracks add centres the
    strict operating score missed; the first two frames answer as without; off, nothing is added."""
    frames = [frame.cube for frame in simulate_sequence("small", 4, seed=7)]
    strict = ModelSpec(name="small", detector="checkpoints/detector.pt", segmenter="checkpoints/segmenter.pt",
                       score_threshold=0.6)
    answers = {}
    for priors in (None, 0.05):
        client = client_for(make_settings(models=[strict], stream_track_priors=priors))
        stream_id = client.post("/v1/streams").json()["id"]
        answers[priors] = [_frame(client, stream_id, seq, cube).json() for seq, cube in enumerate(frames)]
    assert [a["prior_seeds"] for a in answers[None]] == [0, 0, 0, 0]
    seeded = [a["prior_seeds"] for a in answers[0.05]]
    assert seeded[:2] == [0, 0] and sum(seeded[2:]) >= 1, seeded
    for plain, primed in zip(answers[None][:2], answers[0.05][:2], strict=True):
        assert plain["objects"] == primed["objects"]
    assert sum(len(a["objects"]) for a in answers[0.05][2:]) >= sum(len(a["objects"]) for a in answers[None][2:])
