"""The station's start-up objects are out of the garbage collector's full collections while
it runs, and back in when it stops; cyclic garbage made while it runs is still collected."""

from __future__ import annotations

import gc
import weakref

import httpx
import pytest

from server.config import Settings
from server.loopback import BackgroundServer, free_port


class _Node:
    def __init__(self) -> None:
        self.me = self  # a reference cycle: only the collector frees it


@pytest.mark.one_database
def test_a_full_collection_walks_what_the_station_made_since_start_up(settings: Settings) -> None:
    walked_before = len(gc.get_objects())
    station = BackgroundServer(settings, free_port())  # the station, in this process
    station.start()
    try:
        assert httpx.get(f"{station.url}/api/health").status_code == 200
        frozen = gc.get_freeze_count()
        # the modules, routes and objects of start-up: the bulk of the heap, never walked
        assert frozen > walked_before / 2
        assert len(gc.get_objects()) < frozen / 4
        garbage = _Node()
        gone = weakref.ref(garbage)
        del garbage
        gc.collect()
        assert gone() is None
    finally:
        station.stop()
    assert gc.get_freeze_count() == 0  # a stopped station leaves the heap as it found it
    # the start-up objects are walked again (a few may have been freed meanwhile by the
    # threads of other tests in this process)
    assert len(gc.get_objects()) >= 0.99 * frozen
