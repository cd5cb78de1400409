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
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct
from pathlib import Path

WORKER_NICE = 10  # where idle priority is refused: well below the station's live link
AUTOGROUP = Path("/proc/self/autogroup")  # this session's scheduling group (Linux)
AUTOGROUP_NICE = 19  # the group's least share of the CPU: the worker's session yields
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


def yield_to_the_station() -> None:
    """The calling thread, and the threads and processes it starts afterwards (call it
    before starting any), below a station on the same machine: the longest time slice, idle priority, and its session's scheduling group
    at the least weight when the session is its own. Calling it again is harmless."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_IDLE:  # from idle there is no way back
            ask_long_slice()
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (OSError, AttributeError):  # not Linux, or idle priority refused
        try:
            os.nice(WORKER_NICE)
        except OSError:
            pass
    if os.getsid(0) == os.getpid():  # the session, and so its group, is this worker's alone
        try:
            AUTOGROUP.write_text(f"{AUTOGROUP_NICE}\n")
        except OSError:  # no autogroups (disabled, not Linux): the priority above suffices
            pass
