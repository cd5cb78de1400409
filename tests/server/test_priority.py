"""A worker's processes below the station: idle priority with the longest time slice,
inherited by the processes and threads they start."""

from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from server.jobs.priority import LONGEST_SLICE_NS

CHILD = """
import os, threading
from server.jobs.priority import ask_long_slice, yield_to_the_station

def sched(path="/proc/thread-self/sched"):
    return {l.split(":")[0].strip(): l.split(":")[1].strip() for l in open(path) if ":" in l}

assert ask_long_slice()
print(sched()["se.slice"])
yield_to_the_station()
yield_to_the_station()  # again, from idle priority: harmless
seen = []
t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
t.start(); t.join()
pid = os.fork()
if pid == 0:
    os._exit(0 if os.sched_getscheduler(0) == os.SCHED_IDLE else 1)
print(os.sched_getscheduler(0) == os.SCHED_IDLE, seen == [os.SCHED_IDLE], os.waitpid(pid, 0)[1] == 0)
"""


def _kernel() -> tuple[int, int]:
    major, minor = platform.release().split(".")[:2]
    return int(major), int("".join(c for c in minor if c.isdigit()) or 0)


@pytest.mark.skipif(sys.platform != "linux", reason="Linux scheduling")
def test_a_worker_asks_for_the_longest_slice_then_idles() -> None:
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, check=True
    ).stdout.split("\n")
    if _kernel() >= (6, 12):  # EEVDF with slice requests: the request is what the task has
        assert int(out[0]) == LONGEST_SLICE_NS, out
    assert out[1] == "True True True", out  # idle: the process, its threads, its children


@pytest.mark.skipif(sys.platform != "linux", reason="Linux scheduling")
def test_the_long_slice_keeps_this_process_nice() -> None:
    """The request keeps the process's nice (raising it back would need privileges)."""
    code = "import os\nos.nice(5)\nfrom server.jobs.priority import ask_long_slice\n"
    code += "assert ask_long_slice()\nprint(os.getpriority(os.PRIO_PROCESS, 0))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "5"
