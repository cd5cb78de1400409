"""A worker's CPU priority beside a station on the same machine: its jobs run when the
station's live link does not need the CPU, and give it up the moment the link wakes.

Three Linux mechanisms decide that, each at its own level:

- **Idle priority** (``SCHED_IDLE``) ranks the worker's tasks below every other task of its
  scheduling group; ``nice`` where idle priority is refused.
- **Scheduling groups** (autogroup): each session is a group of its own and groups share
  the CPU by their weight, whatever the priorities of the tasks inside. A worker in a
  session of its own (a service, a container, ``setsid``) lowers its group's weight to the
  least (nice 19). One in a shared session (a terminal's) leaves that group alone: lowering
  it would lower the session's other programs too.
- **Time slices** (EEVDF, Linux 6.12 and later): between groups, a woken task takes the
  core from a running one at once only when it asks for a shorter slice; otherwise it
  waits until the running task's slice ends, milliseconds later. The worker asks for the
  longest slice (100 ms) so that any woken task of the station asks for a shorter one.
  Idle priority takes no slice request; the request made just before, at batch priority,
  stays when the task moves to idle priority, and processes and threads inherit both.
  Older kernels ignore the request.
- **An idle CPU group** (cgroup ``cpu.idle``, Linux 5.15 and later) is the whole group at
  idle priority among the groups beside it: a woken task of any other group takes the
  core at once, whatever the slices. The worker moves itself into the group
  ``steelscan-workers`` beside its own cgroup where it may (root, or a delegated
  hierarchy), and stays where it is when its own group is idle already (a systemd unit
  with ``CPUWeight=idle``). A task in a cgroup of its own leaves its session's autogroup,
  so the two mechanisms above then only order the worker's own tasks.

Where the kernel lets a woken task wait for the tick before it takes the core from a job
(``PREEMPT_NONE`` kernels, within a few milliseconds), the station itself can go first:
**real-time priority** for its threads (:func:`put_the_station_first`, opt-in: it needs
``CAP_SYS_NICE``), which a job's task never holds up.
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
from pathlib import Path

IDLE_GROUP = "steelscan-workers"  # the idle CPU group a worker moves into, beside its own
WORKER_NICE = 10  # where idle priority is refused: well below the station's live link
AUTOGROUP = Path("/proc/self/autogroup")  # this session's scheduling group (Linux)
AUTOGROUP_NICE = 19  # the group's least share of the CPU: the worker's session yields
RAISE_EVERY_S = 2.0  # the station raises the threads it started since, this often
LONGEST_SLICE_NS = 100_000_000  # the longest time slice a task may ask for (Linux)
# sched_setattr(2) has no wrapper in Python's standard library or in glibc
_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "arm64": 274}
_SCHED_ATTR = struct.Struct("IIQiIQQQ")  # size, policy, flags, nice, priority, runtime, ...


def ask_long_slice() -> bool:
    """Batch priority for the calling thread at the process's nice, asking for the longest
    time slice; whether the kernel took the call (a kernel before 6.12 takes it and
    ignores the slice)."""
    number = _SCHED_SETATTR.get(platform.machine())
    if number is None or not hasattr(os, "SCHED_BATCH"):
        return False
    attr = _SCHED_ATTR.pack(
        _SCHED_ATTR.size, os.SCHED_BATCH, 0, os.getpriority(os.PRIO_PROCESS, 0), 0,
        LONGEST_SLICE_NS, 0, 0,
    )  # fmt: skip
    libc = ctypes.CDLL(None, use_errno=True)
    return libc.syscall(number, 0, ctypes.create_string_buffer(attr), 0) == 0


def cpu_cgroup(cgroups: str | None = None, mountinfo: str | None = None) -> Path | None:
    """The folder of this process's CPU cgroup (cgroup v1's ``cpu`` controller, else the
    unified v2 hierarchy), from ``/proc/self/cgroup`` and ``/proc/self/mountinfo`` (their
    text may be given); None where no mount of it is visible."""
    try:
        cgroups = cgroups if cgroups is not None else Path("/proc/self/cgroup").read_text()
        mountinfo = mountinfo if mountinfo is not None else Path("/proc/self/mountinfo").read_text()
    except OSError:  # not Linux
        return None
    paths = {}  # "cpu" (v1) or "" (v2): the path inside its hierarchy
    for line in cgroups.splitlines():
        _, controllers, path = line.split(":", 2)
        if "cpu" in controllers.split(","):
            paths["cpu"] = path
        elif controllers == "" and line.startswith("0:"):
            paths[""] = path
    for key in ("cpu", ""):
        if key not in paths:
            continue
        for line in mountinfo.splitlines():
            fields, _, fs = line.partition(" - ")
            fstype, _, options = (fs.split() + ["", "", ""])[:3]
            root, mount = fields.split()[3:5]
            if (key == "cpu" and fstype == "cgroup" and "cpu" in options.split(",")) or (
                key == "" and fstype == "cgroup2"
            ):
                inside = paths[key]
                if root != "/" and not inside.startswith(root):
                    continue  # the process's group is not under this mount's root
                rel = inside[len(root) :] if root != "/" else inside
                return Path(mount) / rel.lstrip("/")
    return None


def join_idle_group(here: Path | None = None) -> bool:
    """Move this process (its threads, and the processes it starts afterwards) into an idle
    CPU group: ``here`` (this process's CPU cgroup, :func:`cpu_cgroup`) when it is idle
    already, else :data:`IDLE_GROUP` beside it, made idle; whether it now runs in one."""
    here = here if here is not None else cpu_cgroup()
    if here is None:
        return False
    try:
        if (here / "cpu.idle").read_text().strip() == "1":
            return True
    except OSError:  # no cpu.idle here (an older kernel, no cpu controller in v2)
        pass
    group = here / IDLE_GROUP
    made = False
    try:
        try:
            group.mkdir()
            made = True
        except FileExistsError:  # another worker beside this one made it
            pass
        (group / "cpu.idle").write_text("1\n")
        (group / "cgroup.procs").write_text(f"{os.getpid()}\n")
    except OSError:  # not permitted (no root, no delegation) or no cpu.idle: as before
        if made:  # the group this call made is not left behind, empty
            try:
                group.rmdir()
            except OSError:
                pass
        return False
    return True


def yield_to_the_station() -> None:
    """The calling thread, and the threads and processes it starts afterwards (call it
    before starting any), below a station on the same machine: the longest time slice,
    idle priority, an idle CPU group where it may join one (:func:`join_idle_group`), else
    its session's scheduling group at the least weight when the session is its own.
    Calling it again is harmless."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_IDLE:  # from idle there is no way back
            ask_long_slice()
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (OSError, AttributeError):  # not Linux, or idle priority refused
        try:
            os.nice(WORKER_NICE)
        except OSError:
            pass
    if join_idle_group():
        return
    if os.getsid(0) == os.getpid():  # the session, and so its group, is this worker's alone
        try:
            AUTOGROUP.write_text(f"{AUTOGROUP_NICE}\n")
        except OSError:  # no autogroups (disabled, not Linux): the priority above suffices
            pass


def put_the_station_first(priority: int) -> int:
    """Real-time round-robin priority (``SCHED_RR`` at ``priority``, 1-99) for every thread
    of this process, so that a woken thread of the station's live link takes a core from a
    job's task at once. With ``SCHED_RESET_ON_FORK``: the threads and processes they start
    (job and live-view workers among them) begin at normal priority, and the station raises
    its new threads by calling this again (every ``RAISE_EVERY_S``). How many threads were
    raised: 0 where the kernel refuses (neither ``CAP_SYS_NICE`` nor an ``RLIMIT_RTPRIO``
    of ``priority``) or it is not Linux."""
    if not hasattr(os, "SCHED_RR") or not hasattr(os, "SCHED_RESET_ON_FORK"):
        return 0
    policy, param = os.SCHED_RR | os.SCHED_RESET_ON_FORK, os.sched_param(priority)
    raised = 0
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), policy, param)
        except ProcessLookupError:  # the thread ended meanwhile
            continue
        except OSError:  # not permitted
            return 0
        raised += 1
    return raised
