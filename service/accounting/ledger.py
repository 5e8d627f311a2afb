"""The usage ledger: requests, MACs and compute time per tenant and UTC day, behind one database URL.

SQLite (a file, WAL mode, ``BEGIN IMMEDIATE`` write transactions) for one API process, PostgreSQL when
several processes or replicas share it. Every change is one short transaction whose counters are
incremented in the database (``SET macs = macs + :n``), never read-modified-written in Python, so
concurrent requests from any number of processes add up exactly.

Daily MAC quotas are enforced in two atomic steps, so that concurrent requests cannot overrun them:

1. ``reserve``: before inference, a conditional update adds an estimate of the request's MACs to
   ``reserved_macs`` only if ``macs + reserved_macs + estimate <= limit``; otherwise 429 at once. The
   reservation is a *lease*: a row in ``{prefix}leases`` with a deadline, written in the same transaction.
2. ``settle``: after inference, a conditional update moves the request from ``reserved_macs`` to the
   counters only if ``macs + actual <= limit``, and writes the request's row in the same transaction.
   If the actual MACs (which depend on the ROI) no longer fit, the reservation is released, nothing is
   billed and the request is answered 429: the billed total never exceeds the limit.

A process that dies between the two steps leaves its lease behind. Expired leases are reclaimed at
start-up (``reclaim_expired``) and by the tenant's next reservation: each lease row is deleted by exactly
one transaction (``DELETE ... RETURNING``), which alone gives its MACs back, so a lease settled, released
or reclaimed concurrently is never given back twice. The billed counters stay exact throughout.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import uuid
from dataclasses import dataclass

from sqlalchemy import (
    BigInteger,
    Column,
    Date,
    DateTime,
    Engine,
    Index,
    Integer,
    MetaData,
    String,
    Table,
    create_engine,
    event,
    func,
    select,
    text,
    update,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import make_url
from sqlalchemy.pool import NullPool


@dataclass(frozen=True)
class DayTotals:
    """One tenant's counters for one UTC day (compute time in integer microseconds, so sums are exact)."""

    tenant: str
    day: dt.date
    requests: int
    macs: int
    compute_us: int
    reserved_macs: int = 0

    @property
    def compute_seconds(self) -> float:
        return self.compute_us / 1e6


@dataclass(frozen=True)
class Lease:
    """A held reservation: ``macs`` of ``tenant``'s quota for ``day`` until ``expires_at``."""

    id: str
    tenant: str
    day: dt.date
    macs: int
    expires_at: dt.datetime


@dataclass(frozen=True)
class Held:
    """Reservations held now for one tenant and day: leases in force and expired (not yet reclaimed)."""

    leases: int
    macs: int
    expired_leases: int
    expired_macs: int


@dataclass(frozen=True)
class QuotaExceeded:
    """Why a reservation or a settlement was refused."""

    tenant: str
    day: dt.date
    used_macs: int
    reserved_macs: int
    requested_macs: int
    limit_macs: int
    # when the request would fit once reservations in force end: the deadline of the lease that frees enough (the
    # requests holding them end sooner, or their leases are given back then); None: the billed MACs alone leave too
    # little, the quota is spent until the next UTC day
    frees_at: dt.datetime | None = None


def utc_today() -> dt.date:
    return dt.datetime.now(dt.UTC).date()


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def _sqlite_engine(url: str) -> Engine:
    parsed = make_url(url)
    if parsed.database and parsed.database != ":memory:":
        from pathlib import Path

        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(url, connect_args={"timeout": 60, "check_same_thread": False})

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, connection_record):  # noqa: ANN001 (DBAPI hook)
        # Let SQLAlchemy, not the sqlite3 module, decide when a transaction begins (the documented recipe).
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA busy_timeout=60000")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):  # noqa: ANN001
        # Take the write lock up front: no deferred read-then-write upgrade can fail with SQLITE_BUSY.
        conn.exec_driver_sql("BEGIN IMMEDIATE")

    return engine


class Ledger:
    """Per-tenant, per-day usage counters and a row per billed request, in tables named ``{prefix}usage``
    and ``{prefix}requests``."""

    def __init__(self, url: str, *, table_prefix: str = "radarseg_", pool_size: int = 8,
                 timeout_s: float = 3.0) -> None:
        self.url = url
        self.table_prefix = table_prefix
        self.dialect = make_url(url).get_backend_name()
        if self.dialect == "sqlite":
            self.engine = _sqlite_engine(url)
            self._insert = sqlite.insert
        elif self.dialect == "postgresql":
            pool = {"pool_size": pool_size, "max_overflow": pool_size, "pool_pre_ping": True,
                    "pool_timeout": timeout_s}
            # a database that is down or silent fails a call within seconds: the connect timeout, unacknowledged
            # data (tcp_user_timeout) and keepalives, in libpq's terms
            wait_ms = int(timeout_s * 1000)
            connect_args = {"connect_timeout": max(1, int(round(timeout_s))), "tcp_user_timeout": wait_ms,
                            "keepalives": 1, "keepalives_idle": max(1, int(timeout_s)), "keepalives_interval": 1,
                            "keepalives_count": 3}
            self.engine = (create_engine(url, connect_args=connect_args, **pool) if pool_size
                           else create_engine(url, connect_args=connect_args, poolclass=NullPool))
            self._insert = postgresql.insert
        else:
            raise ValueError(f"ledger URL must be sqlite or postgresql, got {self.dialect!r}")
        self.metadata = MetaData()
        self.usage = Table(
            f"{table_prefix}usage", self.metadata,
            Column("tenant", String(64), primary_key=True),
            Column("day", Date, primary_key=True),
            Column("requests", BigInteger, nullable=False, default=0),
            Column("macs", BigInteger, nullable=False, default=0),
            Column("compute_us", BigInteger, nullable=False, default=0),
            Column("reserved_macs", BigInteger, nullable=False, default=0),
        )
        self.requests = Table(
            f"{table_prefix}requests", self.metadata,
            Column("id", String(32), primary_key=True),
            Column("tenant", String(64), nullable=False, index=True),
            Column("day", Date, nullable=False),
            Column("model", String(64), nullable=False),
            Column("macs", BigInteger, nullable=False),
            Column("compute_us", BigInteger, nullable=False),
            Column("roi_voxels", Integer, nullable=False),
            Column("created_at", DateTime(timezone=True), nullable=False),
        )
        # a tenant's recent requests of one model: the quota reservation's estimate reads them on every request
        self.recent_index = Index(f"{table_prefix}requests_recent", self.requests.c.tenant, self.requests.c.model,
                                  self.requests.c.created_at)
        self.leases = Table(
            f"{table_prefix}leases", self.metadata,
            Column("id", String(32), primary_key=True),
            Column("tenant", String(64), nullable=False, index=True),
            Column("day", Date, nullable=False),
            Column("macs", BigInteger, nullable=False),
            Column("expires_at", DateTime(timezone=True), nullable=False, index=True),
        )

    def create(self) -> None:
        """Create the tables when missing (idempotent; safe from several processes at once).

        On PostgreSQL, processes starting together would race between "is it there?" and CREATE (a
        DuplicateObject error on the table's type): a transaction-level advisory lock keyed by the table
        prefix serialises them."""
        with self.engine.begin() as conn:
            if self.dialect == "postgresql":
                key = int.from_bytes(hashlib.sha256(self.table_prefix.encode()).digest()[:8], "big", signed=True)
                conn.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": key})
            self.metadata.create_all(conn, checkfirst=True)
            self.recent_index.create(conn, checkfirst=True)  # also on a ledger created before the index existed

    def drop(self) -> None:
        """Drop this ledger's tables (tests clean up their own)."""
        self.metadata.drop_all(self.engine, checkfirst=True)

    def dispose(self) -> None:
        self.engine.dispose()

    def ping(self) -> None:
        """Raise when the database cannot be reached."""
        with self.engine.connect() as conn:
            conn.execute(select(func.count()).select_from(self.usage).limit(1))

    def _ensure_day(self, conn, tenant: str, day: dt.date) -> None:  # noqa: ANN001
        insert = self._insert(self.usage).values(tenant=tenant, day=day, requests=0, macs=0, compute_us=0,
                                                 reserved_macs=0)
        conn.execute(insert.on_conflict_do_nothing(index_elements=["tenant", "day"]))

    def _totals(self, row) -> DayTotals:  # noqa: ANN001
        return DayTotals(row.tenant, row.day, row.requests, row.macs, row.compute_us, row.reserved_macs)

    def reserve(self, tenant: str, macs: int, limit: int, *, lease_s: float = 300.0, day: dt.date | None = None,
                now: dt.datetime | None = None) -> Lease | QuotaExceeded:
        """Hold ``macs`` of ``tenant``'s daily ``limit`` for a request about to run, as a lease that expires
        ``lease_s`` from now; QuotaExceeded when it does not fit. The tenant's expired leases are reclaimed
        first, in the same transaction."""
        day = day or utc_today()
        now = now or utc_now()
        u = self.usage.c
        with self.engine.begin() as conn:
            self._ensure_day(conn, tenant, day)
            self._reclaim(conn, now, tenant)
            held = conn.execute(
                update(self.usage)
                .where(u.tenant == tenant, u.day == day, u.macs + u.reserved_macs + macs <= limit)
                .values(reserved_macs=u.reserved_macs + macs)
                .returning(u.tenant)
            ).first()
            if held is not None:
                lease = Lease(uuid.uuid4().hex, tenant, day, macs, now + dt.timedelta(seconds=lease_s))
                conn.execute(self.leases.insert().values(id=lease.id, tenant=tenant, day=day, macs=macs,
                                                         expires_at=lease.expires_at))
                return lease
            row = conn.execute(select(self.usage).where(u.tenant == tenant, u.day == day)).one()
            frees_at = self._frees_at(conn, tenant, day, row.macs + row.reserved_macs + macs - limit) if (
                row.macs + macs <= limit) else None
        return QuotaExceeded(tenant, day, row.macs, row.reserved_macs, macs, limit, frees_at)

    def check(self, tenant: str, macs: int, limit: int, *, day: dt.date | None = None,
              now: dt.datetime | None = None) -> QuotaExceeded | None:
        """What :meth:`reserve` would refuse, without reserving (a read): QuotaExceeded when ``macs`` more do not
        fit ``tenant``'s ``limit`` beside its billed MACs and its leases in force, else None."""
        day, now = day or utc_today(), now or utc_now()
        u, c = self.usage.c, self.leases.c
        with self.engine.connect() as conn:
            row = conn.execute(select(u.macs).where(u.tenant == tenant, u.day == day)).first()
            used = row.macs if row is not None else 0
            held = int(conn.execute(select(func.coalesce(func.sum(c.macs), 0))
                                    .where(c.tenant == tenant, c.day == day, c.expires_at >= now)).scalar_one())
            if used + held + macs <= limit:
                return None
            frees_at = self._frees_at(conn, tenant, day, used + held + macs - limit) if used + macs <= limit else None
        return QuotaExceeded(tenant, day, used, held, macs, limit, frees_at)

    def _frees_at(self, conn, tenant: str, day: dt.date, missing: int) -> dt.datetime | None:  # noqa: ANN001
        """The deadline by which ``tenant``'s leases in force give back at least ``missing`` MACs."""
        c = self.leases.c
        freed = 0
        for row in conn.execute(select(c.macs, c.expires_at).where(c.tenant == tenant, c.day == day)
                                .order_by(c.expires_at)):
            freed += row.macs
            if freed >= missing:
                expires = row.expires_at
                return expires if expires.tzinfo is not None else expires.replace(tzinfo=dt.UTC)  # SQLite: naive
        return None

    def _give_back(self, conn, leases: list) -> int:  # noqa: ANN001
        """Subtract deleted lease rows (tenant, day, macs) from ``reserved_macs``; the MACs given back."""
        u = self.usage.c
        for row in leases:
            conn.execute(update(self.usage).where(u.tenant == row.tenant, u.day == row.day)
                         .values(reserved_macs=u.reserved_macs - row.macs))
        return sum(row.macs for row in leases)

    def _end_lease(self, conn, lease: Lease) -> int:  # noqa: ANN001
        """Delete ``lease`` and give its MACs back, unless it was already reclaimed; the MACs given back."""
        gone = conn.execute(self.leases.delete().where(self.leases.c.id == lease.id)
                            .returning(self.leases.c.tenant, self.leases.c.day, self.leases.c.macs)).all()
        return self._give_back(conn, gone)

    def _reclaim(self, conn, now: dt.datetime, tenant: str | None) -> int:  # noqa: ANN001
        condition = [self.leases.c.expires_at < now]
        if tenant is not None:
            condition.append(self.leases.c.tenant == tenant)
        gone = conn.execute(self.leases.delete().where(*condition)
                            .returning(self.leases.c.tenant, self.leases.c.day, self.leases.c.macs)).all()
        return self._give_back(conn, gone)

    def reclaim_expired(self, *, now: dt.datetime | None = None, tenant: str | None = None) -> int:
        """Give back every expired lease (of ``tenant``, or of all tenants); the MACs given back."""
        with self.engine.begin() as conn:
            return self._reclaim(conn, now or utc_now(), tenant)

    def release(self, lease: Lease) -> None:
        """Give back the reservation of a request that was not billed (bad input, saturation, failure)."""
        with self.engine.begin() as conn:
            self._end_lease(conn, lease)

    def held(self, tenant: str, day: dt.date | None = None, *, now: dt.datetime | None = None) -> Held:
        """``tenant``'s leases for ``day``: in force and expired (reclaimed by its next reservation)."""
        day, now = day or utc_today(), now or utc_now()
        c = self.leases.c
        expired = (c.expires_at < now)
        query = select(func.count(), func.coalesce(func.sum(c.macs), 0)).where(c.tenant == tenant, c.day == day)
        with self.engine.connect() as conn:
            live = conn.execute(query.where(~expired)).one()
            old = conn.execute(query.where(expired)).one()
        return Held(int(live[0]), int(live[1]), int(old[0]), int(old[1]))

    def recent_max_macs(self, model: str, *, tenant: str | None = None, last: int = 200) -> int:
        """The largest MACs billed for ``model`` among its ``last`` billed requests (of ``tenant`` when given;
        0 when none)."""
        r = self.requests.c
        condition = [r.model == model] if tenant is None else [r.model == model, r.tenant == tenant]
        recent = select(r.macs).where(*condition).order_by(r.created_at.desc()).limit(last).subquery()
        with self.engine.connect() as conn:
            return int(conn.execute(select(func.coalesce(func.max(recent.c.macs), 0))).scalar_one())

    def settle(self, tenant: str, *, model: str, macs: int, compute_us: int, roi_voxels: int = 0,
               lease: Lease | None = None, limit: int | None = None, day: dt.date | None = None,
               request_id: str | None = None) -> DayTotals | QuotaExceeded:
        """Bill one request and end its ``lease`` in one transaction; the day's totals after it.
        With a ``limit``, the request is billed only if the day's billed MACs stay within it; otherwise
        the lease is ended, nothing is billed and QuotaExceeded is returned.
        """
        day = lease.day if lease is not None else (day or utc_today())
        u = self.usage.c
        with self.engine.begin() as conn:
            self._ensure_day(conn, tenant, day)
            if lease is not None:
                self._end_lease(conn, lease)
            condition = [u.tenant == tenant, u.day == day]
            if limit is not None:
                condition.append(u.macs + macs <= limit)
            row = conn.execute(
                update(self.usage).where(*condition)
                .values(requests=u.requests + 1, macs=u.macs + macs, compute_us=u.compute_us + compute_us)
                .returning(*self.usage.c)
            ).first()
            if row is None:
                now = conn.execute(select(self.usage).where(u.tenant == tenant, u.day == day)).one()
                assert limit is not None
                return QuotaExceeded(tenant, day, now.macs, now.reserved_macs, macs, limit)
            conn.execute(self.requests.insert().values(
                id=request_id or uuid.uuid4().hex, tenant=tenant, day=day, model=model, macs=macs,
                compute_us=compute_us, roi_voxels=roi_voxels, created_at=utc_now()))
        return self._totals(row)

    def day_totals(self, tenant: str, day: dt.date | None = None) -> DayTotals:
        """``tenant``'s counters for ``day`` (zeros when it made no request)."""
        day = day or utc_today()
        u = self.usage.c
        with self.engine.connect() as conn:
            row = conn.execute(select(self.usage).where(u.tenant == tenant, u.day == day)).first()
        return self._totals(row) if row is not None else DayTotals(tenant, day, 0, 0, 0)

    def days(self, tenants: list[str] | None = None, *, limit_days: int = 31) -> dict[str, list[DayTotals]]:
        """Each tenant's days, newest first (at most ``limit_days`` each); all tenants when None."""
        query = select(self.usage).order_by(self.usage.c.tenant, self.usage.c.day.desc())
        if tenants is not None:
            query = query.where(self.usage.c.tenant.in_(tenants))
        out: dict[str, list[DayTotals]] = {}
        with self.engine.connect() as conn:
            for row in conn.execute(query):
                days = out.setdefault(row.tenant, [])
                if len(days) < limit_days:
                    days.append(self._totals(row))
        return out

    def all_time(self, tenants: list[str] | None = None) -> dict[str, DayTotals]:
        """Each tenant's totals over every day (``day`` is the latest)."""
        u = self.usage.c
        query = select(u.tenant, func.max(u.day).label("day"), func.sum(u.requests).label("requests"),
                       func.sum(u.macs).label("macs"), func.sum(u.compute_us).label("compute_us")).group_by(u.tenant)
        if tenants is not None:
            query = query.where(u.tenant.in_(tenants))
        with self.engine.connect() as conn:
            return {row.tenant: DayTotals(row.tenant, row.day, int(row.requests), int(row.macs), int(row.compute_us))
                    for row in conn.execute(query)}

    def request_sums(self, tenant: str) -> tuple[int, int, int]:
        """(rows, MACs, compute µs) of the tenant's request rows: equal to its counters' sums by construction."""
        r = self.requests.c
        with self.engine.connect() as conn:
            row = conn.execute(select(func.count(), func.coalesce(func.sum(r.macs), 0),
                                      func.coalesce(func.sum(r.compute_us), 0)).where(r.tenant == tenant)).one()
        return int(row[0]), int(row[1]), int(row[2])
