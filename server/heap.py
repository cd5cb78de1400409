"""The station's Python heap and the garbage collector's pauses.

CPython's full collection (generation 2) walks every container object the process holds
and holds the GIL while it does: in a station with its web framework, database layer,
job queue and image libraries loaded, a quarter of a million objects, 0.1–0.2 s on a
small machine. Every robot's ACKs wait that long. Nearly all of those objects are made at
start-up and live as long as the process (modules, classes, functions, the app's routes),
so after start-up they are moved out of the collector's reach (:func:`gc.freeze`); a full
collection then walks only what the station made since, and the cyclic garbage of a
running station is still collected as before.
"""

from __future__ import annotations

import gc
import logging
import time

log = logging.getLogger(__name__)


def freeze_startup_objects() -> int:
    """Collect once, then move every object the process holds into the collector's
    permanent generation, never walked again; the number of objects moved. Called when
    start-up is over (everything it imports and builds is loaded)."""
    t0 = time.perf_counter()
    gc.collect()
    gc.freeze()
    frozen = gc.get_freeze_count()
    log.info(
        "%d start-up objects out of the garbage collector's full collections (%.0f ms)",
        frozen,
        (time.perf_counter() - t0) * 1000,
    )
    return frozen
