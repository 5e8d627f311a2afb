"""Stream frames racing a DELETE, the expiry clean-up of another create, and a claim running out: the ledger equals
the sum of the billed answers' compute in each race, an unbilled answer carries no compute, and a billed one
carries its compute and request id."""

from __future__ import annotations

import asyncio
import datetime as dt
from collections.abc import Callable

import numpy as np
import pytest

from radar.simulate import simulate_sequence
from tests.service.conftest import NPY, npy_bytes


@pytest.fixture(scope="module")
def cubes() -> list[np.ndarray]:
    return [frame.cube for frame in simulate_sequence("small", 3, seed=31)]


def _during_inference(client, hook: Callable[[], None]) -> None:
    """Run ``hook`` once, when the next frame's inference starts (after its claim, before its result is kept)."""
    served = client.app.state.service.pool.models["tiny"]
    original = served.run

    async def run(cube, **kwargs):
        served.run = original
        hook()
        return await original(cube, **kwargs)

    served.run = run


def _frame(client, stream_id: str, seq: int, cube: np.ndarray):
    return client.post(f"/v1/streams/{stream_id}/frames?seq={seq}", content=npy_bytes(cube), headers=NPY)


def _ledger_matches(client, answers: list) -> None:
    """The tenant's billed requests and MACs equal the sum over the answers that carry compute; no other answer
    carries compute."""
    billed = [a.json() for a in answers if a.status_code == 200]
    assert all("compute" not in a.json() and "request_id" not in a.json() for a in answers if a.status_code != 200)
    assert all(b["request_id"] and b["compute"]["macs"]["total"] > 0 for b in billed)
    total = client.get("/v1/usage").json()["tenants"][0]["total"]
    assert (total["requests"], total["macs"]) == (len(billed), sum(b["compute"]["macs"]["total"] for b in billed))


def test_a_frame_whose_stream_is_deleted_while_it_runs_is_a_404_stream_closed_and_not_billed(
        make_settings, client_for, cubes):
    client = client_for(make_settings(warmup=False))
    state = client.app.state.service
    stream_id = client.post("/v1/streams").json()["id"]
    answers = [_frame(client, stream_id, 0, cubes[0])]
    _during_inference(client, lambda: state.streams.delete("anonymous", stream_id))
    answers.append(_frame(client, stream_id, 1, cubes[1]))
    closed = answers[-1]
    assert closed.status_code == 404 and closed.json()["error"] == "stream_closed", closed.text
    assert "not billed" in closed.json()["detail"]
    _ledger_matches(client, answers)
    assert client.get(f"/v1/streams/{stream_id}").status_code == 404


def test_the_expiry_clean_up_of_a_create_spares_a_stream_a_frame_holds(make_settings, client_for, cubes):
    client = client_for(make_settings(stream_idle_s=1, warmup=False))
    state = client.app.state.service
    stream_id = client.post("/v1/streams").json()["id"]
    later = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=5)  # the stream's last use is past stream_idle_s then

    def create_later() -> None:  # another create of the tenant, its clean-up seeing this stream expired
        assert not isinstance(state.streams.create("anonymous", "tiny", now=later), str)

    _during_inference(client, create_later)
    answers = [_frame(client, stream_id, 0, cubes[0])]
    assert answers[0].status_code == 200, answers[0].text
    assert answers[0].json()["stream"]["frames"] == 1
    _ledger_matches(client, answers)


def test_a_claim_never_runs_out_under_a_running_frame(make_settings, client_for, cubes):
    """A frame running past ``stream_claim_s`` keeps its stream (the claim is renewed): another frame meanwhile is
    refused busy, unbilled; the running one is a 200 billed once."""
    client = client_for(make_settings(stream_claim_s=1, warmup=False))
    state = client.app.state.service
    stream_id = client.post("/v1/streams").json()["id"]
    served = state.pool.models["tiny"]
    original = served.run
    taken = {}

    async def slow_run(cube, **kwargs):
        served.run = original
        await asyncio.sleep(1.8)  # past the claim's first deadline, the event loop free to renew it
        taken["claim"] = state.streams.claim("anonymous", stream_id, 2)
        return await original(cube, **kwargs)

    served.run = slow_run
    answers = [_frame(client, stream_id, 1, cubes[1])]
    assert taken["claim"] == "busy", taken  # the renewed claim held the stream against the next frame
    assert answers[-1].status_code == 200, answers[-1].text
    _ledger_matches(client, answers)


def test_a_frame_whose_claim_was_taken_writes_nothing_and_is_not_billed(make_settings, client_for, cubes):
    client = client_for(make_settings(warmup=False))
    state = client.app.state.service
    stream_id = client.post("/v1/streams").json()["id"]
    later = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=120)  # past the claim: as if its replica had died

    def steal() -> None:
        stolen = state.streams.claim("anonymous", stream_id, 5, now=later)
        state.streams.commit(stolen, {"version": 1, "tracks": []}, now=later)

    _during_inference(client, steal)
    answers = [_frame(client, stream_id, 0, cubes[0])]
    lost = answers[0]
    assert lost.status_code == 409 and lost.json()["error"] == "stream_claim_lost", lost.text
    _ledger_matches(client, answers)
    assert client.get(f"/v1/streams/{stream_id}").json()["last_seq"] == 5  # the other frame's write stands


def test_too_many_streams_says_to_retry_when_the_first_stream_expires(make_settings, client_for):
    client = client_for(make_settings(warmup=False, max_streams_per_tenant=1, stream_idle_s=120))
    assert client.post("/v1/streams").status_code == 201
    refused = client.post("/v1/streams")
    assert refused.status_code == 429 and refused.json()["error"] == "too_many_streams"
    assert 115 <= int(refused.headers["retry-after"]) <= 121, refused.headers  # not 1: a slot frees on expiry


def test_log_lines_escape_the_control_characters_of_names(caplog):
    import logging

    from service.http.public_text import EscapeControlCharacters

    record = logging.LogRecord("service", logging.INFO, __file__, 1, "model %s ready: preset %s", ("tiny",
                               "lab\r\n2026-01-01 INFO forged"), None)
    assert EscapeControlCharacters().filter(record)
    assert record.getMessage() == "model tiny ready: preset lab\\r\\n2026-01-01 INFO forged"
