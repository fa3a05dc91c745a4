"""Settings of the planning service, read from the environment (prefix ``PLANNER_``).

Every setting can be given as an environment variable, e.g. ``PLANNER_PORT=9000`` or
``PLANNER_API_KEYS=key-one,key-two``. Lists accept a comma-separated string or a JSON array.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import (BaseSettings, NoDecode, PydanticBaseSettingsSource,
                               SettingsConfigDict)

#: Hard limits of the planning library (``optimizer.problem``); settings may only tighten them.
LIBRARY_MAX_SAMPLES = 20001
LIBRARY_MAX_TIME_LIMIT = 600.0
LIBRARY_MAX_SWEEP_POINTS = 5001
LIBRARY_MIN_JOINTS = 3
LIBRARY_MAX_JOINTS = 8
LIBRARY_MAX_CONSTRAINT_POINTS = 8
LIBRARY_MIN_DURATION = 1e-3
LIBRARY_MAX_DURATION = 1e4


def _cpu_count() -> int:
    return max(1, os.cpu_count() or 1)


class Settings(BaseSettings):
    """Service configuration.

    Attributes
    ----------
    host, port : str, int
        Where ``python -m service`` listens.
    workers : int
        Solver worker processes (default: the number of CPUs).
    queue_size : int
        Requests that may wait for a worker; one more is answered 503 ``overloaded`` at once.
    retry_after : int
        Seconds advertised in ``Retry-After`` of a 503 answer.
    max_body_bytes : int
        Largest accepted request body (bytes); a larger one is answered 413.
    max_samples : int
        Upper bound of a plan's ``samples``.
    max_joints : int
        Largest number of joints n of a request (3..8; robot constants, start/goal, transform
        rows, robustness starts, ``GET /v1/robots/default?n=``).
    max_constraint_points : int
        Most constraint points in one plan request.
    max_duration : float
        Largest ``duration`` T (s) of a plan (and time of a constraint point).
    max_batch_size, max_robustness_runs, max_sweep_points, max_transform_points : int
        Upper bounds of ``/v1/plans/batch`` requests, robustness runs, sweep points and
        transform points per request.
    max_total_samples : int
        Path rows one answer may hold (sum of a batch's ``samples``; robustness runs x
        ``samples`` with ``include_paths``), which bounds the size of any answer.
    default_time_limit, max_time_limit : float
        Seconds a solve may take when the request gives no ``time_limit``, and the largest
        ``time_limit`` accepted. The service waits ``time_limit + timeout_grace`` at most.
    timeout_grace : float
        Seconds added to a job's time limit before its worker is killed.
    worker_start_timeout : float
        Seconds a new worker may take to start and warm up.
    shutdown_timeout : float
        On SIGTERM, seconds the server waits for requests in flight to finish (uvicorn's
        ``timeout_graceful_shutdown``); what is still queued or running shortly before that is
        answered 503 ``shutting_down``, then the workers stop.
    queue_timeout : float
        Seconds a request may wait for a free worker before 503 ``overloaded``.
    worker_ping_interval, worker_ping_timeout : float
        Each idle worker is pinged every ``worker_ping_interval`` s and replaced when it does
        not answer within ``worker_ping_timeout`` s (0 interval: no pings).
    max_connections : int
        Open client connections; more are answered 503 at once and closed (lowered to fit
        the file descriptor limit).
    header_timeout : float
        Seconds a client may take to send a request's headers (and a new connection its first
        byte) before the connection is closed.
    keep_alive_timeout : int
        Seconds an idle keep-alive connection stays open (uvicorn's ``timeout_keep_alive``).
    http : {"httptools", "h11"}
        uvicorn's HTTP implementation (the bounds hold with either; httptools costs less CPU).
    max_header_bytes : int
        Largest request line plus headers; more is 431.
    body_timeout : float
        Seconds a request's whole body may take to arrive before 408 ``request_timeout``.
    send_timeout : float
        Seconds an answer may wait for the client to read a chunk of it (64 KiB) before the
        connection is dropped.
    start_method : {"forkserver", "spawn"}
        How worker processes are created (never plain ``fork`` of a threaded server).
    warmup : bool
        Build the default robot's chained form in every worker before it takes work.
    native_cache : str
        Directory of compiled NLP functions, ``auto`` (the user's cache directory) or ``off``.
    api_keys : list of str
        Accepted keys (``X-API-Key`` header or ``Authorization: Bearer``); empty: no auth.
    cors_origins : list of str
        Allowed CORS origins; empty: CORS off.
    log_level : str
    """

    model_config = SettingsConfigDict(env_prefix="PLANNER_", extra="ignore")

    host: str = Field(default="0.0.0.0", description="Listen address.")
    port: int = Field(default=8000, ge=1, le=65535, description="Listen port.")
    workers: int = Field(default_factory=_cpu_count, ge=1, le=256,
                         description="Solver worker processes.")
    worker_nice: int = Field(default=5, ge=0, le=19,
                             description="Niceness of the worker processes (the event loop "
                                         "keeps the CPU first: shorter latency tails).")
    queue_size: int = Field(default=64, ge=0, le=100_000,
                            description="Requests allowed to wait.")
    retry_after: int = Field(default=1, ge=1, le=3600,
                             description="Retry-After seconds of a 503.")
    max_body_bytes: int = Field(default=1 << 20, ge=1024,
                                description="Largest request body, bytes.")
    max_samples: int = Field(default=LIBRARY_MAX_SAMPLES, ge=2, le=LIBRARY_MAX_SAMPLES)
    max_joints: int = Field(default=LIBRARY_MAX_JOINTS, ge=LIBRARY_MIN_JOINTS,
                            le=LIBRARY_MAX_JOINTS)
    max_constraint_points: int = Field(default=LIBRARY_MAX_CONSTRAINT_POINTS, ge=0,
                                       le=LIBRARY_MAX_CONSTRAINT_POINTS)
    max_duration: float = Field(default=LIBRARY_MAX_DURATION, ge=1.0, le=LIBRARY_MAX_DURATION)
    max_batch_size: int = Field(default=64, ge=1, le=10_000)
    max_robustness_runs: int = Field(default=200, ge=1, le=100_000)
    max_sweep_points: int = Field(default=2001, ge=2, le=LIBRARY_MAX_SWEEP_POINTS)
    max_transform_points: int = Field(default=10_000, ge=1, le=1_000_000)
    max_total_samples: int = Field(default=200_000, ge=2,
                                   description="Path rows one answer may hold: the sum of a "
                                               "batch's samples, or robustness runs x samples "
                                               "with include_paths.")
    default_time_limit: float = Field(default=10.0, gt=0, le=LIBRARY_MAX_TIME_LIMIT)
    max_time_limit: float = Field(default=60.0, gt=0, le=LIBRARY_MAX_TIME_LIMIT)
    timeout_grace: float = Field(default=0.5, ge=0, le=60)
    worker_start_timeout: float = Field(default=120.0, gt=0)
    shutdown_timeout: float = Field(default=30.0, gt=0, le=3600)
    queue_timeout: float = Field(default=30.0, gt=0, le=3600)
    worker_ping_interval: float = Field(default=1.0, ge=0, le=3600)
    worker_ping_timeout: float = Field(default=1.0, gt=0, le=3600)
    max_connections: int = Field(default=1000, ge=1, le=1_000_000)
    header_timeout: float = Field(default=10.0, gt=0, le=3600)
    keep_alive_timeout: int = Field(default=5, ge=1, le=3600)
    http: Literal["httptools", "h11"] = "httptools"
    max_header_bytes: int = Field(default=16384, ge=1024, le=1 << 20)
    body_timeout: float = Field(default=30.0, gt=0, le=3600)
    send_timeout: float = Field(default=30.0, gt=0, le=3600)
    start_method: Literal["forkserver", "spawn"] = "forkserver"
    warmup: bool = True
    native_cache: str = Field(
        default="auto", min_length=1,
        description="Directory of the compiled NLP functions (optimizer.native; built once "
                    "per machine in the background with the C compiler): 'auto' for "
                    "$XDG_CACHE_HOME/chained-planner/native, 'off' for CasADi's virtual "
                    "machine only.")
    api_keys: Annotated[list[str], NoDecode] = Field(default_factory=list)
    cors_origins: Annotated[list[str], NoDecode] = Field(default_factory=list)
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("api_keys", "cors_origins", mode="before")
    @classmethod
    def _split_list(cls, value: Any) -> Any:
        """Accept ``a,b`` or a JSON array for list settings."""
        if isinstance(value, str):
            text = value.strip()
            if text.startswith("["):
                return json.loads(text)
            return [part.strip() for part in text.split(",") if part.strip()]
        return value

    @property
    def native_cache_dir(self) -> str | None:
        """``native_cache`` as a directory, or None when off."""
        value = self.native_cache.strip()
        if value.lower() == "off":
            return None
        if value.lower() == "auto":
            from optimizer.native import default_cache_dir
            return str(default_cache_dir())
        return value

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower(cls, value: Any) -> Any:
        return value.lower() if isinstance(value, str) else value

    @model_validator(mode="after")
    def _consistent(self) -> "Settings":
        if self.default_time_limit > self.max_time_limit:
            raise ValueError("default_time_limit must not exceed max_time_limit")
        return self

    @property
    def limits(self) -> "Limits":
        """The subset of settings that shapes the request schemas (and so the OpenAPI)."""
        return Limits(max_samples=self.max_samples, max_batch_size=self.max_batch_size,
                      max_joints=self.max_joints,
                      max_constraint_points=self.max_constraint_points,
                      max_duration=self.max_duration,
                      max_robustness_runs=self.max_robustness_runs,
                      max_sweep_points=self.max_sweep_points,
                      max_transform_points=self.max_transform_points,
                      max_total_samples=self.max_total_samples,
                      default_time_limit=self.default_time_limit,
                      max_time_limit=self.max_time_limit)


@dataclass(frozen=True)
class Limits:
    """Request bounds that appear in the schemas (hashable, so schemas are built once each)."""

    max_samples: int = LIBRARY_MAX_SAMPLES
    max_batch_size: int = 64
    max_joints: int = LIBRARY_MAX_JOINTS
    max_constraint_points: int = LIBRARY_MAX_CONSTRAINT_POINTS
    max_duration: float = LIBRARY_MAX_DURATION
    max_robustness_runs: int = 200
    max_sweep_points: int = 2001
    max_transform_points: int = 10_000
    max_total_samples: int = 200_000
    default_time_limit: float = 10.0
    max_time_limit: float = 60.0


class _DefaultsOnly(Settings):
    """Settings that read neither the environment nor dotenv files."""

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings],
                                   init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings,)


def default_settings(**overrides: Any) -> Settings:
    """Settings from their defaults and ``overrides`` only, ignoring the environment.

    Used for the committed OpenAPI document and in tests, so that neither depends on the
    machine's ``PLANNER_*`` variables.
    """
    return _DefaultsOnly(**overrides)
