"""One router per resource of the REST API, and the browsers' websockets."""

from server.api.routes import (
    auth,
    clouds,
    coverage,
    defects,
    foxglove,
    frames,
    jobs,
    live,
    preferences,
    reports,
    results,
    robots,
    sessions,
    structure_history,
    structures,
    telemetry,
    timeline,
    users,
    view3d,
)

ROUTERS = [
    r.router
    for r in (
        auth,
        preferences,
        sessions,
        frames,
        clouds,
        telemetry,
        timeline,
        coverage,
        defects,
        structures,
        structure_history,
        results,
        reports,
        jobs,
        users,
        robots,
        live,
        view3d,
        foxglove,
    )
]
