"""All settings of the ground station, from ``STEELSCAN_*`` environment variables."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

PROJECT_ROOT = Path(__file__).resolve().parent.parent


class Settings(BaseSettings):
    """Ground-station settings; every field can be set as ``STEELSCAN_<NAME>``."""

    model_config = SettingsConfigDict(env_prefix="STEELSCAN_", extra="ignore")

    data_dir: Path = Field(default=Path("steelscan-data"), description="where sessions live")
    database_url: str | None = Field(default=None, description="defaults to SQLite in data_dir")
    host: str = "127.0.0.1"
    port: int = 8765
    max_message_bytes: int = 8 * 1024 * 1024
    max_import_bytes: int = Field(
        default=50 * 1024**3, description="largest MCAP file POST /api/sessions/import accepts"
    )
    tls_cert: Path | None = Field(
        default=None, description="PEM certificate: serve HTTPS and wss:// (with tls_key)"
    )
    tls_key: Path | None = Field(default=None, description="PEM private key of tls_cert")
    max_connections_per_client: int = Field(
        default=64, ge=1, description="open connections one address may hold (robots, browsers)"
    )
    max_connections: int = Field(
        default=0,
        ge=0,
        description="open connections the station holds in all (0: what its open-file limit, "
        "raised at start, leaves beside 256 for files)",
    )
    max_pending_connections: int = Field(
        default=256,
        ge=1,
        description="connections still sending their request head, station-wide; a new one "
        "closes the longest-waiting",
    )
    max_body_bytes: int = Field(
        default=1024 * 1024,
        ge=1024,
        description="largest request body of any route but the MCAP import (max_import_bytes)",
    )
    body_grace_s: float = Field(
        default=20.0,
        gt=0,
        description="time a request body has beyond its size at body_min_rate_bps (else 408)",
    )
    body_min_rate_bps: float = Field(
        default=64 * 1024, gt=0, description="slowest a request body may arrive, bytes a second"
    )
    body_idle_s: float = Field(
        default=15.0, gt=0, description="longest pause inside a request body (else 408)"
    )
    max_live_sessions_per_robot: int = Field(
        default=4,
        ge=1,
        description="live sessions one robot may hold; its next SESSION_START ends the oldest",
    )
    request_head_timeout_s: float = Field(
        default=10.0, gt=0, description="time a client has to send a request's line and headers"
    )
    robot_messages_per_s: float = Field(
        default=3000.0, description="rate limit per robot connection (ERROR, retry, beyond it)"
    )
    robot_message_burst: float = Field(
        default=500.0, description="messages a robot may send at once before the rate limit"
    )
    browser_messages_per_s: float = Field(
        default=100.0, description="rate limit per browser connection (stop and e-stop always pass)"
    )
    browser_message_burst: float = Field(
        default=50.0, description="messages a browser may send at once before the rate limit"
    )
    max_browser_message_bytes: int = Field(
        default=16 * 1024, description="largest message a browser may send (commands are small)"
    )
    min_free_bytes: int = Field(
        default=256 * 1024 * 1024,
        ge=0,
        description="free disk space kept in the data directory: below it robots are told "
        "to send again later",
    )
    session_idle_s: float = Field(
        default=1800.0,
        gt=0,
        description="a live session with no message for this long is ended by the station "
        "(its robot never sent SESSION_END) and its files closed",
    )
    fsync: bool = Field(default=False, description="fsync every stored file (power-loss safety)")
    job_workers: int = Field(
        default=2, ge=1, description="worker processes for processing jobs (job_backend local)"
    )
    job_backend: Literal["local", "celery"] = Field(
        default="local",
        description="where jobs run: the station's own worker processes, or Celery workers "
        "(steelscan worker, on this or other machines mounting the same data_dir)",
    )
    broker_url: str = Field(
        default="redis://127.0.0.1:6379/0", description="Celery's broker (job_backend celery)"
    )
    job_lease_s: float = Field(
        default=60.0,
        gt=0,
        description="a running job whose worker has not been heard of for this long is "
        "handed to another worker",
    )
    realtime_priority: int = Field(
        default=0,
        ge=0,
        le=99,
        description="real-time (SCHED_RR) priority of the station's threads, so that job "
        "workers on the same machine never keep its live link waiting (needs CAP_SYS_NICE, "
        "e.g. docker's cap_add: [SYS_NICE]); 0: off",
    )
    job_fanout: int = Field(
        default=4,
        ge=0,
        description="other workers a Celery job asks to help with its independent parts "
        "(frames, pairs, segments)",
    )
    worker_threads: int = Field(
        default=1,
        ge=1,
        description="threads one job uses on a Celery worker process (scale with processes)",
    )
    auto_process: bool = Field(default=True, description="run jobs when a session ends")
    coverage_mm_per_px: float = Field(
        default=0.3,
        gt=0,
        description="coarsest camera resolution (mm of surface per pixel) that counts as "
        "imaged in the coverage map and report",
    )
    detect_method: Literal["proposed", "learned"] = Field(
        default="learned",
        description="crack detector of the detect job: the shipped network or the filter pipeline",
    )
    web_dir: Path = PROJECT_ROOT / "web"
    live_queue: int = Field(default=8, description="frames buffered per watching browser")
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="pages of other origins (scheme://host:port) "
        "whose browser websockets are accepted; the station's own always are",
    )
    view3d: bool = Field(
        default=True, description="serve the 3D view (viser, proxied under /viser/)"
    )
    view3d_port: int = Field(
        default=0,
        description="loopback port of the live 3D view's viser server (0: any free one; session views always take free ones)",
    )
    live_map: bool = Field(
        default=True,
        description="grow the 3D map during a session (ICP in a worker process) and show it",
    )
    foxglove_port: int | None = Field(
        default=None,
        ge=0,
        le=65535,
        description="port of the live Foxglove server (foxglove-sdk) that clients reach "
        "through the station's authenticated /foxglove websocket; None: off, 0: any free one",
    )
    foxglove_host: str = Field(
        default="127.0.0.1",
        description="where the live Foxglove server listens: loopback, so that every client "
        "comes through /foxglove with a token; on any other address it takes clients "
        "without one",
    )
    live_detect: bool = Field(
        default=True,
        description="search each frame for defects as it arrives (a worker process) and show "
        "them on the Drive page's coverage map",
    )

    def uvicorn_options(self) -> dict[str, Any]:
        """What ``uvicorn.Config`` needs of these settings: TLS, the connection guard, the
        websocket message size."""
        from server.link.guard import guarded_http

        tls = (
            {"ssl_certfile": str(self.tls_cert), "ssl_keyfile": str(self.tls_key)}
            if self.tls_cert is not None
            else {}
        )
        return {
            **tls,
            "http": guarded_http(
                self.max_connections_per_client,
                self.request_head_timeout_s,
                max_connections=self.max_connections,
                max_pending=self.max_pending_connections,
            ),
            "ws_max_size": self.ws_max_bytes,
            "ws_per_message_deflate": False,  # media does not deflate: it would only cost CPU
        }

    @property
    def ws_max_bytes(self) -> int:
        """Largest websocket message read: twice the protocol limit, so a message somewhat
        over it is answered with the protocol's ERROR (naming its seq, which the robot then
        drops); beyond this the connection is closed (1009) before it is read."""
        return 2 * self.max_message_bytes + 2**16

    @model_validator(mode="after")
    def _tls_pair(self) -> Settings:
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        return self

    def resolved_database_url(self) -> str:
        """The database URL, SQLite in the data directory unless set."""
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'steelscan.db').resolve()}"
