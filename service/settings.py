"""Service settings (pydantic-settings, environment prefix ``RADARSEG_``).

Every field can be set from the environment: scalars as text (``RADARSEG_PORT=8080``), lists and
mappings as JSON (``RADARSEG_API_KEYS='{"a-long-random-key-1234": "acme"}'``). Validators refuse values
that would make the service unsafe or unusable: a non-loopback bind without API keys, short keys,
tenant names that could not be metric labels, unbounded bodies or queues, unknown database schemes.

Relative checkpoint paths are resolved against the repository root (the directory holding
``service/``), so the defaults serve the shipped model from any working directory.
"""

from __future__ import annotations

import ipaddress
import logging
import os
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from models.runtime import Runtime
from radar.centres import MAX_OBJECTS, SCORE_THRESHOLD

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
TENANT_PATTERN = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
TABLE_PREFIX_PATTERN = re.compile(r"^[a-z][a-z0-9_]{0,30}$")
MIN_KEY_LENGTH = 16
MAX_BODY_LIMIT = 1 << 30  # never accept more than 1 GiB in one request
ANONYMOUS_TENANT = "anonymous"
DEPLOYMENT_NAME = "radarseg"  # the service's Ray Serve deployment (service.ray_serve)

# The shipped checkpoints of the `small` preset (committed under checkpoints/ by the training issue).
DEFAULT_DETECTOR = "checkpoints/detector.pt"
DEFAULT_SEGMENTER = "checkpoints/segmenter.pt"
# The slimmed pair (pruned at ratio 0.4 and fine-tuned; docs/guides/slimming.md, docs/results.md), served beside
# them by default as ?model=small-p40.
SLIMMED_DETECTOR = "checkpoints/detector-slimmed.pt"
SLIMMED_SEGMENTER = "checkpoints/segmenter-slimmed.pt"


def resolve_path(path: str | Path) -> Path:
    """``path`` as given when absolute, else relative to the repository root."""
    path = Path(path).expanduser()
    return path if path.is_absolute() else REPO_ROOT / path


class ModelSpec(BaseModel):
    """One served model: a name clients pick with ``?model=``, and its two checkpoints."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_.-]{0,63}$")]
    detector: Path
    segmenter: Path
    score_threshold: Annotated[float, Field(ge=0.0, le=1.0)] = SCORE_THRESHOLD
    max_objects: Annotated[int, Field(ge=1, le=256)] = MAX_OBJECTS
    # What runs the pair (models.runtime): torch (PyTorch and the compiled sparse kernels), torch-int8 (the
    # segmenter in the int8 sparse kernels, each replica calibrated at load on simulated frames of the model's preset:
    # docs/guides/int8.md), onnx (the exported graphs in onnxruntime, exported on first load into $RADARSEG_ONNX_CACHE,
    # default ~/.cache/radarseg/onnx) or onnx-int8 (those graphs statically quantised)
    runtime: Literal["torch", "torch-int8", "onnx", "onnx-int8"] = "torch"

    @model_validator(mode="before")
    @classmethod
    def _former_engine_and_precision(cls, data: Any) -> Any:
        """The former keys "engine" and "precision" name a runtime still (logged with the key that replaces them)."""
        if not isinstance(data, dict) or ("engine" not in data and "precision" not in data):
            return data
        data = dict(data)
        engine, precision = data.pop("engine", "torch"), data.pop("precision", "float")
        if not isinstance(engine, str) or not isinstance(precision, str):
            raise ValueError("engine and precision are names (now one key: runtime)")
        try:
            former = Runtime.from_engine(engine, precision).name
        except ValueError as exc:
            raise ValueError(str(exc)) from None
        if data.setdefault("runtime", former) != former:
            raise ValueError(f"runtime {data['runtime']!r} and the former engine/precision ({former}) disagree")
        log.warning("model %r: \"engine\"/\"precision\" are now one key: \"runtime\": %r", data.get("name"), former)
        return data


class Settings(BaseSettings):
    """Configuration of one API process."""

    model_config = SettingsConfigDict(env_prefix="RADARSEG_", extra="forbid", frozen=True)

    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8000
    models: Annotated[list[ModelSpec], Field(min_length=1)] = [
        ModelSpec(name="small", detector=Path(DEFAULT_DETECTOR), segmenter=Path(DEFAULT_SEGMENTER)),
        ModelSpec(name="small-p40", detector=Path(SLIMMED_DETECTOR), segmenter=Path(SLIMMED_SEGMENTER)),
    ]
    default_model: str | None = None  # None: the first of `models`
    replicas: Annotated[int, Field(ge=1, le=16)] = 1  # model instances per model (each runs one request at a time)
    max_queue: Annotated[int, Field(ge=0, le=1024)] = 8  # requests waiting per model beyond the running ones
    retry_after_s: Annotated[int, Field(ge=1, le=3600)] = 1
    warmup: bool = True  # run each model once at start-up (the first torch call of a process is slow)
    # torch intra-op threads of each replica's inference thread; None: OMP_NUM_THREADS if set, else the CPUs
    # divided among the replicas
    torch_threads: Annotated[int | None, Field(ge=1, le=256)] = None
    # OpenMP's thread count as the environment gives it (OMP_NUM_THREADS, no prefix: Ray sets it to an actor's CPUs)
    omp_num_threads: Annotated[int | None, Field(ge=1, le=4096, validation_alias=AliasChoices(
        "omp_num_threads", "OMP_NUM_THREADS"))] = None
    # What the models layer reads from the environment, declared here so that every setting of the service is in
    # this object: the app exports the ones set (service.main) before any model loads. onnx_cache: where the onnx
    # engines' exports are kept (default ~/.cache/radarseg/onnx); onnx_cache_key_file: the secret that seals them
    # (default ~/.config/radarseg/onnx-cache.key); sparse_kernels: the sparse convolutions' kernels (models.sparse)
    onnx_cache: Path | None = None
    onnx_cache_key_file: Path | None = None
    sparse_kernels: Annotated[str | None, Field(max_length=32)] = None
    # a complex128 carrada cube (256 x 256 x 64) and its header; the header check refuses other shapes early
    max_body_bytes: Annotated[int, Field(ge=1024, le=MAX_BODY_LIMIT)] = 64 * 2**20 + 65536

    # Uploads are read before a request takes a model slot; these bound slow and numerous uploaders.
    body_min_rate: Annotated[int, Field(ge=1, le=2**30)] = 65536  # bytes/s a body must average after the grace
    body_grace_s: Annotated[float, Field(ge=0.1, le=600)] = 5.0  # seconds before the minimum rate applies
    body_timeout_s: Annotated[float, Field(ge=1, le=3600)] = 120.0  # a whole body within this, whatever its rate
    body_idle_s: Annotated[float, Field(ge=0.5, le=600)] = 30.0  # a body sending nothing this long is cut off (408)
    max_uploads: Annotated[int, Field(ge=1, le=4096)] = 64  # bodies being received at once (503 beyond)
    max_upload_bytes: Annotated[int, Field(ge=1024, le=16 * 2**30)] = 512 * 2**20  # their announced bytes
    max_tenant_uploads: Annotated[int, Field(ge=1, le=4096)] = 8  # the same bounds per tenant
    max_tenant_upload_bytes: Annotated[int, Field(ge=1024, le=16 * 2**30)] = 2 * (64 * 2**20 + 65536)
    # HTTP head limits (the `service.server.http_server` runner enforces them before the app sees a request): 431 beyond
    max_header_bytes: Annotated[int, Field(ge=1024, le=2**20)] = 65536  # request line and headers together
    max_headers: Annotated[int, Field(ge=8, le=1000)] = 100
    header_timeout_s: Annotated[float, Field(ge=0.5, le=600)] = 30.0  # a request head complete within this (408)
    # writing one answer: from the first time the client's socket stops taking it, the answer must be taken within
    # this, or the connection is cut (a client reading at 100 bytes/s holds no buffer for long)
    write_timeout_s: Annotated[float, Field(ge=0.5, le=3600)] = 60.0
    # Connections (the `service.server.http_server` runner): at most this many open at once; a new one beyond closes the
    # connection that has waited longest for a request head (idle keep-alive or a stalled head), or is refused
    # with 503 when every one is busy. None: the process's file limit (RLIMIT_NOFILE, raised to its hard limit
    # when allowed) less FILE_RESERVE descriptors for the ledger, checkpoints and logs, at most 4096.
    max_connections: Annotated[int | None, Field(ge=2, le=65536)] = None
    keep_alive_s: Annotated[float, Field(ge=0.5, le=600)] = 5.0  # an idle connection between requests (uvicorn's)
    max_json_depth: Annotated[int, Field(ge=2, le=64)] = 16  # nesting of a JSON header (X-Cube-Schema)
    # a JSON request body (POST /v1/streams): read only after the key is checked, held in the upload gate, 413 beyond
    max_json_body_bytes: Annotated[int, Field(ge=256, le=2**20)] = 16384

    api_keys: dict[SecretStr, str] = {}  # key -> tenant; none configured = one anonymous tenant
    admin_tenants: list[str] = []  # tenants whose keys may read every tenant's usage
    allow_anonymous_remote: bool = False  # serve without keys on a non-loopback address

    daily_mac_quota: Annotated[int | None, Field(ge=0)] = None  # per tenant and UTC day; None: unlimited
    tenant_quotas: dict[str, Annotated[int, Field(ge=0)]] = {}  # per-tenant overrides of daily_mac_quota
    # a reservation is a lease: one left by a crashed process is given back after this many seconds
    lease_s: Annotated[float, Field(ge=1, le=86400)] = 300.0
    reservation_headroom: Annotated[float, Field(ge=1.0, le=100.0)] = 1.5  # times the largest segmenter MACs known

    # the ledger's database: its calls run on ledger_threads threads of their own (never the threads the plain
    # routes use), each at most ledger_timeout_s (a silent database is a 503 then, not a hung request); while it
    # is down, requests that need it answer 503 at once and a probe every ledger_check_s finds it back
    ledger_threads: Annotated[int, Field(ge=1, le=64)] = 4
    ledger_timeout_s: Annotated[float, Field(gt=0, le=60)] = 3.0
    ledger_check_s: Annotated[float, Field(gt=0, le=60)] = 1.0

    # streams (POST /v1/streams): their tracker state lives in the ledger's database, so any replica serves the
    # next frame; a stream unused this long has expired; a frame holds its stream at most stream_claim_s (a
    # replica that dies mid-frame frees it then); a tenant holds at most max_streams_per_tenant live streams
    stream_idle_s: Annotated[float, Field(ge=1, le=86400)] = 300.0
    stream_claim_s: Annotated[float, Field(ge=1, le=3600)] = 30.0
    max_streams_per_tenant: Annotated[int, Field(ge=1, le=10000)] = 16
    # a detector that reads earlier frames gets a stream's frames before this one from the replica that ran them
    # (service/streams/history.py), kept as float16 within this many bytes over every stream (0: never kept)
    stream_history_bytes: Annotated[int, Field(ge=0, le=2**36)] = 256 * 2**20
    # tracks as priors (radar/track_priors.py): where a stream's confirmed track predicts an object that no centre
    # above the operating score stands for, the detector's best centre within 3 m scored at least this seeds region
    # growing too (None: off, the default)
    stream_track_priors: Annotated[float | None, Field(gt=0, lt=1)] = None

    # the example sequences of GET /v1/examples (each simulated once per radar, unbilled) kept within this many bytes
    example_cache_bytes: Annotated[int, Field(ge=0, le=2**34)] = 128 * 2**20

    data_dir: Path = Path("data/service")  # relative to the working directory
    ledger_url: str | None = None  # None: SQLite (WAL) file ledger.sqlite3 under data_dir
    ledger_table_prefix: str = "radarseg_"

    @field_validator("api_keys")
    @classmethod
    def _check_keys(cls, keys: dict[SecretStr, str]) -> dict[SecretStr, str]:
        for key, tenant in keys.items():
            secret = key.get_secret_value()
            if len(secret) < MIN_KEY_LENGTH or secret != secret.strip():
                raise ValueError(f"API key of tenant {tenant!r} must be at least {MIN_KEY_LENGTH} characters "
                                 "without surrounding spaces")
            if not TENANT_PATTERN.match(tenant):
                raise ValueError(f"tenant name {tenant!r} must match {TENANT_PATTERN.pattern}")
        return keys

    @field_validator("ledger_table_prefix")
    @classmethod
    def _check_prefix(cls, prefix: str) -> str:
        if not TABLE_PREFIX_PATTERN.match(prefix):
            raise ValueError(f"ledger_table_prefix {prefix!r} must match {TABLE_PREFIX_PATTERN.pattern}")
        return prefix

    @field_validator("ledger_url")
    @classmethod
    def _check_url(cls, url: str | None) -> str | None:
        if url is not None and not url.startswith(("sqlite://", "postgresql://", "postgresql+psycopg://")):
            raise ValueError(f"ledger_url must be a sqlite:// or postgresql+psycopg:// URL, got {url.split(':')[0]}://")
        return url

    @model_validator(mode="after")
    def _check_consistency(self) -> Settings:
        names = [m.name for m in self.models]
        if len(set(names)) != len(names):
            raise ValueError(f"model names must be unique, got {names}")
        if self.default_model is not None and self.default_model not in names:
            raise ValueError(f"default_model {self.default_model!r} is not one of the models {names}")
        tenants = set(self.api_keys.values())
        if unknown := sorted(set(self.admin_tenants) - tenants):
            raise ValueError(f"admin_tenants {unknown} have no API key")
        if unknown := sorted(set(self.tenant_quotas) - (tenants or {ANONYMOUS_TENANT})):
            raise ValueError(f"tenant_quotas name unknown tenants {unknown}")
        if self.body_timeout_s <= self.body_grace_s:
            raise ValueError(f"body_timeout_s ({self.body_timeout_s}) must exceed body_grace_s ({self.body_grace_s})")
        if self.max_upload_bytes < self.max_body_bytes:
            raise ValueError(f"max_upload_bytes ({self.max_upload_bytes}) must hold at least one body of "
                             f"max_body_bytes ({self.max_body_bytes})")
        if self.max_tenant_upload_bytes < self.max_body_bytes:
            raise ValueError(f"max_tenant_upload_bytes ({self.max_tenant_upload_bytes}) must hold at least one body "
                             f"of max_body_bytes ({self.max_body_bytes})")
        if not self.api_keys and not self.allow_anonymous_remote and not _is_loopback(self.host):
            raise ValueError(f"refusing to serve on {self.host!r} without API keys: configure api_keys, bind "
                             "127.0.0.1, or set allow_anonymous_remote explicitly")
        return self

    @property
    def model_names(self) -> list[str]:
        return [m.name for m in self.models]

    @property
    def default_model_name(self) -> str:
        return self.default_model or self.models[0].name

    def tenant_for_key(self) -> dict[str, str]:
        """Plain key -> tenant (used once, to build the authenticator)."""
        return {key.get_secret_value(): tenant for key, tenant in self.api_keys.items()}

    @property
    def inference_threads(self) -> int:
        """torch threads per replica: ``torch_threads``, else ``OMP_NUM_THREADS`` when set (Ray sets it to an
        actor's CPUs), else the CPUs shared among the replicas."""
        if self.torch_threads is None and self.omp_num_threads is not None:
            return self.omp_num_threads
        return self.torch_threads or max(1, (os.cpu_count() or 1) // self.replicas)

    def models_environment(self) -> dict[str, str]:
        """The environment variables the models layer reads, as these settings give them (the ones set)."""
        named = {"RADARSEG_ONNX_CACHE": self.onnx_cache, "RADARSEG_ONNX_CACHE_KEY_FILE": self.onnx_cache_key_file,
                 "RADARSEG_SPARSE_KERNELS": self.sparse_kernels}
        return {name: str(value) for name, value in named.items() if value is not None}

    @property
    def tenants(self) -> list[str]:
        """Every tenant the service can bill: the key owners, or the anonymous tenant."""
        return sorted(set(self.api_keys.values())) or [ANONYMOUS_TENANT]

    def quota_for(self, tenant: str) -> int | None:
        """Daily MAC quota of ``tenant`` (None: unlimited)."""
        return self.tenant_quotas.get(tenant, self.daily_mac_quota)

    def resolved_ledger_url(self) -> str:
        """The database URL of the usage ledger (the SQLite default under ``data_dir``)."""
        if self.ledger_url is not None:
            return self.ledger_url
        return f"sqlite:///{(Path(self.data_dir).expanduser().absolute() / 'ledger.sqlite3').as_posix()}"


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
