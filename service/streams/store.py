"""Streams of frames: their tracker state, kept in the ledger's database so that any replica serves a stream's
next frame and a restarted replica loses no track.

A row per stream in ``{prefix}streams``: its tenant, model, last frame number (``seq``), the tracker's JSON state
(:meth:`radar.tracking.Tracker.to_state`, a few KB), when it was last used, and a *claim*. A frame takes the
claim in one conditional update (free, or left expired by a replica that died mid-frame), runs, and writes the
new state and ``seq`` under the same claim token while giving it back: two frames of one stream never run at
once, on one replica or several, and a frame whose claim was lost writes nothing. A stream unused for
``idle_s`` has expired: it answers as gone and its row is deleted by the tenant's next ``create``. Each tenant
holds at most ``max_per_tenant`` live streams (counted and inserted in one transaction, under a PostgreSQL
advisory lock per tenant; SQLite's write transactions are serial already).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import uuid
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from sqlalchemy import BigInteger, Column, DateTime, String, Table, Text, delete, func, select, text, update

from service.accounting.ledger import Ledger, utc_now


class Refusal(StrEnum):
    """Why a stream operation was refused."""

    missing = "missing"  # no such stream for this tenant (or another tenant's: never said)
    expired = "expired"
    busy = "busy"  # another frame of the stream holds its claim
    stale = "stale"  # seq not after the stream's last frame
    too_many = "too_many"  # the tenant's cap on open streams
    closed = "closed"  # deleted (DELETE) while a frame held it: the frame's result is not kept
    lost = "lost"  # the frame's claim ran out and another frame took the stream: nothing written


@dataclass(frozen=True)
class StreamRow:
    """A stream as stored (``state`` is the tracker's JSON state, None before its first frame)."""

    id: str
    tenant: str
    model: str
    created_at: dt.datetime
    updated_at: dt.datetime
    last_seq: int | None
    frames: int
    state: dict[str, Any] | None

    def expires_at(self, idle_s: float) -> dt.datetime:
        return self.updated_at + dt.timedelta(seconds=idle_s)


@dataclass(frozen=True)
class Claim:
    """A frame's hold on its stream: the stream as it was when claimed, and the token that writes it back."""

    stream: StreamRow
    token: str
    seq: int

    @property
    def gap(self) -> int:
        """Frame periods since the stream's last frame (1: none missed; the first frame counts 1)."""
        return 1 if self.stream.last_seq is None else self.seq - self.stream.last_seq


def _aware(value: dt.datetime) -> dt.datetime:
    return value if value.tzinfo is not None else value.replace(tzinfo=dt.UTC)  # SQLite keeps them naive


class StreamStore:
    """The ``{prefix}streams`` table beside the ledger's (created by ``Ledger.create``); every method is one
    short transaction (blocking: the service calls them on the ledger's threads)."""

    def __init__(self, ledger: Ledger, *, idle_s: float, claim_s: float, max_per_tenant: int) -> None:
        self.ledger = ledger
        self.idle_s, self.claim_s, self.max_per_tenant = idle_s, claim_s, max_per_tenant
        self.table = Table(
            f"{ledger.table_prefix}streams", ledger.metadata,
            Column("id", String(32), primary_key=True),
            Column("tenant", String(64), nullable=False, index=True),
            Column("model", String(64), nullable=False),
            Column("created_at", DateTime(timezone=True), nullable=False),
            Column("updated_at", DateTime(timezone=True), nullable=False),
            Column("last_seq", BigInteger, nullable=True),
            Column("frames", BigInteger, nullable=False, default=0),
            Column("state", Text, nullable=True),
            Column("claim_token", String(32), nullable=True),
            Column("claimed_until", DateTime(timezone=True), nullable=True),
        )

    def _row(self, row: Any) -> StreamRow:
        return StreamRow(row.id, row.tenant, row.model, _aware(row.created_at), _aware(row.updated_at), row.last_seq,
                         int(row.frames), None if row.state is None else json.loads(row.state))

    def _live_since(self, now: dt.datetime) -> dt.datetime:
        return now - dt.timedelta(seconds=self.idle_s)

    def create(self, tenant: str, model: str, *, now: dt.datetime | None = None) -> StreamRow | Refusal:
        """A new stream of ``tenant`` on ``model``; Refusal.too_many at the tenant's cap. The tenant's expired
        streams are deleted first."""
        now = now or utc_now()
        c = self.table.c
        with self.ledger.engine.begin() as conn:
            if self.ledger.dialect == "postgresql":
                key = int.from_bytes(hashlib.sha256(f"{self.table.name}/{tenant}".encode()).digest()[:8], "big",
                                     signed=True)
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": key})
            # expired streams go, but never one a frame still holds (its claim is live): that frame commits
            unclaimed = c.claimed_until.is_(None) | (c.claimed_until < now)
            conn.execute(delete(self.table).where(c.tenant == tenant, c.updated_at < self._live_since(now),
                                                  unclaimed))
            live = conn.execute(select(func.count()).where(c.tenant == tenant)).scalar_one()
            if live >= self.max_per_tenant:
                return Refusal.too_many
            stream_id = uuid.uuid4().hex
            conn.execute(self.table.insert().values(id=stream_id, tenant=tenant, model=model, created_at=now,
                                                    updated_at=now, last_seq=None, frames=0, state=None))
        return StreamRow(stream_id, tenant, model, now, now, None, 0, None)

    def get(self, tenant: str, stream_id: str, *, now: dt.datetime | None = None) -> StreamRow | Refusal:
        now = now or utc_now()
        c = self.table.c
        with self.ledger.engine.connect() as conn:
            row = conn.execute(select(self.table).where(c.id == stream_id, c.tenant == tenant)).first()
        if row is None:
            return Refusal.missing
        stream = self._row(row)
        return Refusal.expired if stream.updated_at < self._live_since(now) else stream

    def delete(self, tenant: str, stream_id: str) -> bool:
        """Close a stream (its tracks are gone); False when the tenant has no such stream."""
        c = self.table.c
        with self.ledger.engine.begin() as conn:
            gone = conn.execute(delete(self.table).where(c.id == stream_id, c.tenant == tenant).returning(c.id))
            return gone.first() is not None

    def check(self, tenant: str, stream_id: str, seq: int, *, now: dt.datetime | None = None) -> StreamRow | Refusal:
        """What :meth:`claim` would say of frame ``seq``, without claiming (before a body is read)."""
        stream = self.get(tenant, stream_id, now=now)
        if isinstance(stream, Refusal):
            return stream
        return Refusal.stale if stream.last_seq is not None and seq <= stream.last_seq else stream

    def claim(self, tenant: str, stream_id: str, seq: int, *, now: dt.datetime | None = None) -> Claim | Refusal:
        """Take the stream for frame ``seq``: free (or its claim expired), live, and ``seq`` after its last frame."""
        now = now or utc_now()
        c = self.table.c
        token = uuid.uuid4().hex
        free = (c.claimed_until.is_(None)) | (c.claimed_until < now)
        in_order = c.last_seq.is_(None) | (c.last_seq < seq)
        with self.ledger.engine.begin() as conn:
            row = conn.execute(
                update(self.table)
                .where(c.id == stream_id, c.tenant == tenant, c.updated_at >= self._live_since(now), free, in_order)
                .values(claim_token=token, claimed_until=now + dt.timedelta(seconds=self.claim_s))
                .returning(*self.table.c)
            ).first()
        if row is not None:
            return Claim(self._row(row), token, seq)
        stream = self.check(tenant, stream_id, seq, now=now)
        return stream if isinstance(stream, Refusal) else Refusal.busy

    def commit(self, claim: Claim, state: dict[str, Any], *, now: dt.datetime | None = None) -> Refusal | None:
        """Write the tracker state after frame ``claim.seq`` and give the claim back (None); Refusal.closed when
        the stream was deleted meanwhile, Refusal.lost when the claim was lost (it ran out and another frame took
        the stream): nothing is written then."""
        now = now or utc_now()
        c = self.table.c
        with self.ledger.engine.begin() as conn:
            done = conn.execute(
                update(self.table).where(c.id == claim.stream.id, c.claim_token == claim.token)
                .values(state=json.dumps(state), last_seq=claim.seq, frames=c.frames + 1, updated_at=now,
                        claim_token=None, claimed_until=None)
                .returning(c.id)
            ).first()
            if done is not None:
                return None
            exists = conn.execute(select(c.id).where(c.id == claim.stream.id)).first()
        return Refusal.lost if exists is not None else Refusal.closed

    def extend(self, claim: Claim, *, now: dt.datetime | None = None) -> bool:
        """Push the claim's deadline ``claim_s`` past ``now`` while its frame still runs; False when it is lost."""
        now = now or utc_now()
        c = self.table.c
        with self.ledger.engine.begin() as conn:
            done = conn.execute(update(self.table).where(c.id == claim.stream.id, c.claim_token == claim.token)
                                .values(claimed_until=now + dt.timedelta(seconds=self.claim_s)).returning(c.id))
            return done.first() is not None

    def next_free_in(self, tenant: str, *, now: dt.datetime | None = None) -> float:
        """Seconds until the tenant's first live stream expires (a slot frees then, or on a DELETE before)."""
        now = now or utc_now()
        c = self.table.c
        with self.ledger.engine.connect() as conn:
            oldest = conn.execute(select(func.min(c.updated_at)).where(c.tenant == tenant)).scalar_one()
        if oldest is None:
            return 0.0
        return max(0.0, (_aware(oldest) + dt.timedelta(seconds=self.idle_s) - now).total_seconds())

    def release(self, claim: Claim) -> None:
        """Give the claim back without writing (the frame failed or was refused)."""
        c = self.table.c
        with self.ledger.engine.begin() as conn:
            conn.execute(update(self.table).where(c.id == claim.stream.id, c.claim_token == claim.token)
                         .values(claim_token=None, claimed_until=None))
