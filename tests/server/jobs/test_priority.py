"""A worker's processes below the station: idle priority with the longest time slice, and
an idle CPU group where the worker may join one, inherited by the processes and threads
they start."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import pytest

from server.jobs.priority import IDLE_GROUP, LONGEST_SLICE_NS, cpu_cgroup, join_idle_group

STARTED = """
import os, threading

def started():
    '''The scheduling policies of a thread and of a process this one starts.'''
    seen = []
    t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
    t.start(); t.join()
    pid = os.fork()
    if pid == 0:
        os._exit(os.sched_getscheduler(0))
    return seen[0], os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
"""

CHILD = (
    STARTED
    + """
from server.jobs.priority import ask_long_slice, yield_to_the_station

def sched(path="/proc/thread-self/sched"):
    return {l.split(":")[0].strip(): l.split(":")[1].strip() for l in open(path) if ":" in l}

assert ask_long_slice()
print(sched()["se.slice"])
yield_to_the_station()
yield_to_the_station()  # again, from idle priority: harmless
thread, child = started()
print(os.sched_getscheduler(0) == os.SCHED_IDLE, thread == os.SCHED_IDLE, child == os.SCHED_IDLE)
"""
)


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


# /proc/self/cgroup and /proc/self/mountinfo as a hybrid host (cgroup v1 controllers and the
# unified hierarchy) and a container (its groups' roots mounted at the top) show them
HYBRID_CGROUP = "4:memory:/user.slice\n1:cpu,cpuacct:/user.slice/term\n0::/user.slice/term\n"
HYBRID_MOUNTS = (
    "30 25 0:26 / /sys/fs/cgroup/unified rw - cgroup2 cgroup2 rw\n"
    "33 25 0:29 / /sys/fs/cgroup/cpu,cpuacct rw - cgroup cgroup rw,cpu,cpuacct\n"
)
V2_CGROUP = "0::/system.slice/steelscan.service\n"
V2_MOUNTS = "25 20 0:22 / /sys/fs/cgroup rw,nosuid - cgroup2 cgroup2 rw,nsdelegate\n"
CONTAINER_CGROUP = "0::/docker/abc\n"
CONTAINER_MOUNTS = "25 20 0:22 /docker/abc /sys/fs/cgroup ro - cgroup2 cgroup2 rw\n"


@pytest.mark.parametrize(
    ("cgroups", "mounts", "expected"),
    [
        (HYBRID_CGROUP, HYBRID_MOUNTS, "/sys/fs/cgroup/cpu,cpuacct/user.slice/term"),
        (V2_CGROUP, V2_MOUNTS, "/sys/fs/cgroup/system.slice/steelscan.service"),
        (CONTAINER_CGROUP, CONTAINER_MOUNTS, "/sys/fs/cgroup"),
        (V2_CGROUP, HYBRID_MOUNTS.splitlines()[1], None),  # no mount of its hierarchy
    ],
)
def test_the_cpu_cgroup_is_found_on_v1_v2_and_in_a_container(
    cgroups: str, mounts: str, expected: str | None
) -> None:
    found = cpu_cgroup(cgroups, mounts)
    assert (str(found) if found else None) == expected


def test_a_group_that_is_idle_already_is_kept(tmp_path: Path) -> None:
    (tmp_path / "cpu.idle").write_text("1\n")
    assert join_idle_group(tmp_path)
    assert not (tmp_path / IDLE_GROUP).exists()  # a systemd unit's CPUWeight=idle: stays


def test_a_group_the_worker_may_not_change_leaves_it_where_it_is(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    (locked / IDLE_GROUP).write_text("a file, not a folder: mkdir is refused\n")
    assert not join_idle_group(locked)


def test_a_group_made_but_refused_idleness_is_not_left_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_write = Path.write_text

    def refuse_idle(path: Path, text: str, *args, **kwargs) -> int:  # type: ignore[no-untyped-def]
        if path.name == "cpu.idle":
            raise PermissionError(f"{path}: not permitted")
        return real_write(path, text, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", refuse_idle)
    assert not join_idle_group(tmp_path)
    assert not (tmp_path / IDLE_GROUP).exists()


IDLE_CHILD = """
import os, subprocess
from server.jobs.priority import IDLE_GROUP, cpu_cgroup, yield_to_the_station
yield_to_the_station()
group = cpu_cgroup()
child = subprocess.run(["cat", "/proc/self/cgroup"], capture_output=True, text=True).stdout
print(group.name == IDLE_GROUP, (group / "cpu.idle").read_text().strip(), IDLE_GROUP in child)
"""


def _may_make_idle_groups() -> bool:
    here = cpu_cgroup()
    return (
        here is not None
        and (here / "cpu.idle").exists()
        and os.access(here, os.W_OK)
        and here.name != IDLE_GROUP
    )


@pytest.mark.skipif(not _may_make_idle_groups(), reason="no writable cgroup with cpu.idle")
def test_a_worker_joins_an_idle_cpu_group_its_children_inherit() -> None:
    out = subprocess.run(
        [sys.executable, "-c", IDLE_CHILD], capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["True", "1", "True"], out


STATION_CHILD = (
    STARTED
    + """
from server.jobs.priority import put_the_station_first

RR = os.SCHED_RR | os.SCHED_RESET_ON_FORK
before = threading.Thread(target=threading.Event().wait, daemon=True)
before.start()
raised = put_the_station_first(10)
thread, child = started()
print(raised, os.sched_getscheduler(0) == RR, os.sched_getscheduler(before.native_id) == RR,
      thread == os.SCHED_OTHER, child == os.SCHED_OTHER, os.sched_param(10) == os.sched_getparam(0))
"""
)


@pytest.mark.skipif(os.geteuid() != 0, reason="real-time priority needs CAP_SYS_NICE")
def test_the_station_goes_first_and_what_it_starts_does_not() -> None:
    """Every thread of the station at real-time priority; the threads and processes they
    start (job and live-view workers) at normal priority until raised; refused without the
    capability."""
    out = subprocess.run(
        [sys.executable, "-c", STATION_CHILD], capture_output=True, text=True, check=True
    ).stdout.split()
    assert out == ["2", "True", "True", "True", "True", "True"], out
    refused = subprocess.run(
        ["setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", "--", sys.executable,
         "-c", "from server.jobs.priority import put_the_station_first as f; print(f(10))"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert refused.stdout.split() == ["0"], refused


@pytest.mark.skipif(os.geteuid() != 0, reason="real-time priority needs CAP_SYS_NICE")
def test_a_station_set_to_go_first_raises_its_threads_started_later(tmp_path: Path) -> None:
    from server.jobs.priority import RAISE_EVERY_S
    from server.loopback import free_port, serve_process

    log = tmp_path / "serve.log"
    proc = serve_process(
        tmp_path / "data",
        free_port(),
        log=log,
        STEELSCAN_REALTIME_PRIORITY="10",
        STEELSCAN_VIEW3D="false",
        STEELSCAN_AUTO_PROCESS="false",
    )
    try:
        rr = os.SCHED_RR | os.SCHED_RESET_ON_FORK
        deadline = time.monotonic() + 4 * RAISE_EVERY_S
        while True:
            policies = {os.sched_getscheduler(int(t)) for t in os.listdir(f"/proc/{proc.pid}/task")}
            if policies == {rr} or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert policies == {rr}, policies  # those answering the health check's too
        assert "real-time priority 10" in log.read_text()
    finally:
        proc.terminate()
        proc.wait(timeout=30)
