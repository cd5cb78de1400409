"""Build the FastAPI app: lifespan (database, migrations, jobs), routers, static dashboard."""

from __future__ import annotations

import asyncio
import gc
import json
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from pathlib import Path

import anyio
from fastapi import Depends, FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from sqlalchemy.exc import DataError
from starlette.types import Scope

from server.api.accounts import accounts_exist, user_for_token
from server.api.bodies import BodyLimits, RequestBodies
from server.api.deps import get_current_user
from server.api.headers import SecurityHeaders
from server.api.routes import ROUTERS
from server.api.routes.reports import IMPORT_PATH
from server.config import Settings
from server.errors import Conflict, NotFound
from server.heap import freeze_startup_objects
from server.jobs.priority import RAISE_EVERY_S, put_the_station_first
from server.link.connection import router as robot_router
from server.link.guard import raise_fd_limit
from server.state import AppState

log = logging.getLogger(__name__)


async def _end_quiet_sessions(state: AppState) -> None:
    """Every little while: close the files of quiet sessions, end the live ones whose robot
    went silent without SESSION_END, and process those as if it had ended them."""
    idle = state.settings.session_idle_s
    while True:
        await asyncio.sleep(min(60.0, idle / 4))
        try:
            ended = await anyio.to_thread.run_sync(state.ingest.close_quiet_sessions, idle)
        except Exception:  # noqa: BLE001  the next round tries again
            log.exception("could not end quiet sessions")
            continue
        for sid in ended:
            log.info("session %s ended: no message for %g s", sid, idle)
            if state.settings.auto_process:
                await anyio.to_thread.run_sync(state.jobs.enqueue_pipeline, sid)


async def _keep_the_station_first(priority: int) -> None:
    """The station's threads at real-time ``priority``, those it starts later included
    (:func:`~server.jobs.priority.put_the_station_first`); a warning where it is refused."""
    raised = put_the_station_first(priority)
    if not raised:
        log.warning(
            "real-time priority %d refused (the station needs CAP_SYS_NICE): its live link "
            "runs at normal priority",
            priority,
        )
        return
    log.info("real-time priority %d for the station's %d threads", priority, raised)
    while True:
        await asyncio.sleep(RAISE_EVERY_S)
        put_the_station_first(priority)


async def may_send_body(scope: Scope, token: str | None) -> bool:
    """Whether a request may have its body read: a valid bearer token (any role: the route
    checks its own), or no accounts yet."""
    state = scope["app"].state.steelscan

    def check() -> bool:
        with state.factory() as db:
            return not accounts_exist(db) or user_for_token(db, token) is not None

    return await anyio.to_thread.run_sync(check)


def create_app(settings: Settings | None = None) -> FastAPI:
    """The ground-station ASGI app."""
    settings = settings or Settings()
    # the API docs serve Swagger/ReDoc from the station itself: no CDN on a bridge
    app = FastAPIOffline(
        title="steelscan ground station",
        version="0.1.0",
        lifespan=_lifespan(settings),
        description="Live link, storage, processing and review for steel-inspection climbing robots.",
    )
    _add_error_handlers(app)

    @app.get("/api/health", tags=["health"], dependencies=[Depends(get_current_user)])
    def read_health(request: Request) -> dict[str, object]:
        """Liveness, and the data directory's free space: below the reserve robot data is
        refused with "retry later" (``accepting`` false)."""
        space = request.app.state.steelscan.ingest.reserve.status()
        return {
            "status": "ok",
            "storage": {
                "free_bytes": space.free_bytes,
                "reserve_bytes": space.reserve_bytes,
                "accepting": space.accepting,
            },
        }

    app.add_middleware(
        RequestBodies,
        limits=BodyLimits(
            max_bytes=settings.max_body_bytes,
            large=((IMPORT_PATH, settings.max_import_bytes),),
            grace_s=settings.body_grace_s,
            min_rate_bps=settings.body_min_rate_bps,
            idle_s=settings.body_idle_s,
        ),
        authenticate=may_send_body,
        open_paths=frozenset({"/api/auth/token"}),
    )
    app.add_middleware(SecurityHeaders)
    app.include_router(robot_router)
    for router in ROUTERS:
        app.include_router(router)
    _add_web(app, settings.web_dir)
    return app


def _lifespan(settings: Settings) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's services for as long as it runs (:meth:`AppState.open` and ``close``),
    and the station's background tasks."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        log.info("open-file limit: %d", raise_fd_limit())
        state = AppState.open(settings, asyncio.get_running_loop())
        app.state.steelscan = state
        reaper = asyncio.create_task(_end_quiet_sessions(state))
        first = (
            asyncio.create_task(_keep_the_station_first(settings.realtime_priority))
            if settings.realtime_priority
            else None
        )
        freeze_startup_objects()  # a full collection would pause every robot's link
        # data stored after a processing whose re-run was lost with a stop (after the
        # freeze: what it makes is not start-up's)
        caught_up = (
            asyncio.create_task(anyio.to_thread.run_sync(state.jobs.catch_up))
            if settings.auto_process
            else None
        )
        try:
            yield
        finally:
            gc.unfreeze()  # an app run inside another program leaves its heap as it was
            reaper.cancel()
            if caught_up is not None:
                await asyncio.gather(caught_up, return_exceptions=True)
            if first is not None:
                first.cancel()
            state.close()

    return lifespan


def _add_error_handlers(app: FastAPI) -> None:
    """Errors as JSON with the right status."""

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, exc: RequestValidationError) -> Response:
        # as FastAPI's own, written as ASCII: the refused input may hold what UTF-8 cannot
        body = json.dumps({"detail": jsonable_encoder(exc.errors())}, ensure_ascii=True)
        return Response(body, status_code=422, media_type="application/json")

    @app.exception_handler(DataError)
    async def unstorable(_: Request, exc: DataError) -> JSONResponse:
        # a value the database refuses (on PostgreSQL: a NUL in text, a number out of range)
        reason = str(exc.orig).splitlines()[0] if exc.orig is not None else "invalid value"
        return JSONResponse({"detail": f"a value cannot be stored: {reason}"}, status_code=422)

    @app.exception_handler(NotFound)
    async def not_found(_: Request, exc: NotFound) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=404)

    @app.exception_handler(Conflict)
    async def conflict(_: Request, exc: Conflict) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=409)


def _add_web(app: FastAPI, web_dir: Path) -> None:
    """The dashboard's page, its files and its front-end libraries."""

    @app.get("/", include_in_schema=False)
    def read_index(request: Request) -> HTMLResponse:
        # the page learns whether it must ask for a sign-in without calling the API first
        # (an unauthenticated API call would be a 401 in the browser's console)
        with request.app.state.steelscan.factory() as db:
            required = accounts_exist(db)
        html = (web_dir / "index.html").read_text(encoding="utf-8")
        meta = f'<meta name="steelscan-auth" content="{"required" if required else "open"}">'
        return HTMLResponse(
            html.replace("<head>", f"<head>\n{meta}", 1), headers={"Cache-Control": "no-store"}
        )

    app.mount("/static", StaticFiles(directory=web_dir), name="static")
    # front-end libraries installed from npm by scripts/setup.sh (web/package-lock.json): served
    # here, never from a CDN
    for name, folder in (
        ("openseadragon", "openseadragon/build/openseadragon"),
        ("uplot", "uplot/dist"),
    ):
        path = web_dir / "node_modules" / folder
        if path.is_dir():
            app.mount(f"/vendor/{name}", StaticFiles(directory=path), name=f"vendor-{name}")
        else:
            log.warning("web: %s is missing: run scripts/setup.sh (npm ci in web/)", path)
