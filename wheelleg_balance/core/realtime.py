"""
Real-time options for the control thread: SCHED_FIFO priority, CPU pinning, memory locking.

Each function tries one option and returns ``(ok, message)`` instead of raising, so balance_node
can call them at start-up and report the outcome in /diagnostics. They act on the *calling
thread* where Linux allows it (scheduler policy, affinity: pid 0 is the calling task), so call
them from the control thread itself. Memory locking is per process.

Without rights (no root, no ``rtprio`` entry in /etc/security/limits.conf, no CAP_SYS_NICE /
CAP_IPC_LOCK) they return ok False with the reason; the loop still runs, with more jitter.
On a kernel without PREEMPT_RT, SCHED_FIFO still helps against other processes but not against
the kernel's own latency (``kernel_is_preempt_rt`` tells which kernel this is).
``name_thread`` names the control thread for top -H / ps -L (and the benchmark's per-thread CPU).
Linux man pages: sched_setscheduler(2), sched_setaffinity(2), mlockall(2), prctl(2).
"""
import ctypes
import ctypes.util
import os
import platform
from typing import Dict, Iterable, Optional, Tuple

Result = Tuple[bool, str]

# mlockall(2) flags. They differ on a few architectures (powerpc, sparc, alpha use
# 0x2000 / 0x4000 / 0x8000); x86 and arm (the robot computers we target) use 1 / 2 / 4.
_MCL = {'ppc64le': (0x2000, 0x4000, 0x8000), 'ppc64': (0x2000, 0x4000, 0x8000),
        'sparc64': (0x2000, 0x4000, 0x8000)}
_MCL_DEFAULT = (1, 2, 4)
_PR_SET_NAME = 15  # linux/prctl.h


def set_fifo_priority(priority: int, pid: int = 0) -> Result:
    """
    Put the calling thread (pid 0) or task ``pid`` under SCHED_FIFO with ``priority``.

    priority: 1 (lowest) .. 99 on Linux; 0 means "leave the scheduler alone" and returns
    (True, 'not requested'). Needs root, CAP_SYS_NICE or an rtprio limit >= priority.
    """
    if priority == 0:
        return True, 'SCHED_FIFO not requested'
    if not hasattr(os, 'sched_setscheduler'):
        return False, 'SCHED_FIFO unavailable on %s' % platform.system()
    lo = os.sched_get_priority_min(os.SCHED_FIFO)
    hi = os.sched_get_priority_max(os.SCHED_FIFO)
    if not lo <= priority <= hi:
        return False, 'SCHED_FIFO priority %d outside %d..%d' % (priority, lo, hi)
    try:
        os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return False, ('SCHED_FIFO %d refused: %s (needs root, CAP_SYS_NICE or an rtprio '
                       'limit)' % (priority, exc.strerror or exc))
    return True, 'SCHED_FIFO priority %d' % priority


def pin_to_cpus(cpus: Iterable[int], pid: int = 0) -> Result:
    """
    Restrict the calling thread (pid 0) or task ``pid`` to the CPUs ``cpus``.

    An empty set means "leave the affinity alone". CPUs outside the allowed set (cgroup,
    taskset) are refused with the allowed set in the message.
    """
    wanted = {int(c) for c in cpus}
    if not wanted:
        return True, 'CPU pinning not requested'
    if not hasattr(os, 'sched_setaffinity'):
        return False, 'CPU pinning unavailable on %s' % platform.system()
    try:
        allowed = os.sched_getaffinity(pid)
    except OSError as exc:
        return False, 'cannot read CPU affinity: %s' % (exc.strerror or exc)
    if not wanted <= allowed:
        return False, 'CPUs %s not allowed (allowed: %s)' % (
            _cpu_list(wanted - allowed), _cpu_list(allowed))
    try:
        os.sched_setaffinity(pid, wanted)
    except OSError as exc:
        return False, 'CPU pinning to %s refused: %s' % (_cpu_list(wanted), exc.strerror or exc)
    return True, 'pinned to CPU %s' % _cpu_list(wanted)


def lock_memory(future: bool = True, on_fault: bool = False,
                machine: Optional[str] = None) -> Result:
    """
    Lock the process's pages in RAM with mlockall(2), so no page fault stalls the loop.

    future: also lock pages mapped later (MCL_FUTURE). on_fault: lock pages only once touched
    (MCL_ONFAULT, Linux >= 4.4), which keeps large reserved-but-unused mappings (thread stacks,
    DDS pools) from counting against RLIMIT_MEMLOCK. Needs root, CAP_IPC_LOCK or a large enough
    ``ulimit -l``. machine: platform.machine() override (tests).
    """
    libc = _libc()
    if libc is None:
        return False, 'mlockall unavailable: no C library found'
    mcl_current, mcl_future, mcl_onfault = _MCL.get(machine or platform.machine(),
                                                    _MCL_DEFAULT)
    flags = mcl_current | (mcl_future if future else 0) | (mcl_onfault if on_fault else 0)
    try:
        mlockall = libc.mlockall
    except AttributeError:
        return False, 'mlockall unavailable in the C library'
    if mlockall(ctypes.c_int(flags)) != 0:
        err = ctypes.get_errno()
        return False, 'mlockall refused: %s (needs root, CAP_IPC_LOCK or ulimit -l)' % (
            os.strerror(err) if err else 'unknown error')
    return True, 'memory locked (%s)' % '|'.join(
        name for name, on in (('MCL_CURRENT', True), ('MCL_FUTURE', future),
                              ('MCL_ONFAULT', on_fault)) if on)


def unlock_memory() -> Result:
    """Undo lock_memory (munlockall(2))."""
    libc = _libc()
    if libc is None or not hasattr(libc, 'munlockall'):
        return False, 'munlockall unavailable'
    if libc.munlockall() != 0:
        return False, 'munlockall failed: %s' % os.strerror(ctypes.get_errno())
    return True, 'memory unlocked'


def apply(priority: int = 0, cpus: Iterable[int] = (), lock: bool = False) -> Dict[str, Result]:
    """
    Try every requested option from the calling (control) thread.

    The memory lock is MCL_CURRENT | MCL_FUTURE | MCL_ONFAULT: a ROS node reserves large but
    little-touched mappings (thread stacks, DDS pools) that would otherwise count in full
    against RLIMIT_MEMLOCK. Returns {'priority' | 'affinity' | 'memory_lock': (ok, message)}
    for /diagnostics.
    """
    return {
        'priority': set_fifo_priority(priority),
        'affinity': pin_to_cpus(cpus),
        'memory_lock': (lock_memory(future=True, on_fault=True) if lock
                        else (True, 'memory locking not requested')),
    }


def name_thread(name: str) -> Result:
    """
    Give the calling thread a kernel-visible name (prctl PR_SET_NAME, at most 15 bytes).

    Python threads are all called 'python' in top -H, ps -L and /proc/<pid>/task/*/comm;
    with a name, the control thread's CPU use and priority can be watched on the robot.
    """
    libc = _libc()
    if libc is None or not hasattr(libc, 'prctl'):
        return False, 'prctl unavailable'
    raw = name.encode('utf-8', 'replace')[:15]
    if libc.prctl(_PR_SET_NAME, ctypes.c_char_p(raw), 0, 0, 0) != 0:
        return False, 'thread name refused: %s' % os.strerror(ctypes.get_errno())
    return True, 'thread named %r' % raw.decode('utf-8', 'replace')


def kernel_is_preempt_rt() -> bool:
    """Tell whether the kernel is PREEMPT_RT (/sys/kernel/realtime reads 1)."""
    try:
        with open('/sys/kernel/realtime') as f:
            return f.read().strip() == '1'
    except OSError:
        return False


def _libc():
    """Return the C library with errno capture, or None."""
    # The interpreter is linked against libc: its symbols need no library search (and
    # ctypes.util.find_library would run ldconfig in a subprocess).
    for name in _libc_names():
        try:
            lib = ctypes.CDLL(name, use_errno=True)
        except OSError:
            continue
        if hasattr(lib, 'mlockall'):
            return lib
    return None


def _libc_names():
    """Yield None (the interpreter's own symbols), then, only if asked, the searched libc."""
    yield None
    yield ctypes.util.find_library('c')


def _cpu_list(cpus) -> str:
    return ','.join(str(c) for c in sorted(cpus))
