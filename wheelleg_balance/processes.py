"""
balance_node's child processes: started on the parent's package, a failed start in one line.

balance_node runs its control loop, sensor intake and watchdog as processes of their own
(docs/balance_node.md). ``Child`` starts one as ``python -P -m wheelleg_balance.nodes.X``:
``-P`` keeps the working directory off its ``sys.path`` (a copy of the package there would
shadow the installed one), and ``PYTHONPATH`` is the parent's ``sys.path``, the folder the
parent's own package came from first, so the child imports exactly the package its parent runs.
A child whose start fails writes one line (what failed, why, the fix: ``StartError``) into a
pipe of its own that the parent reads; no traceback unless ``WHEELLEG_BALANCE_TRACEBACK=1`` is
set. Once the parent has seen it start, the pipe is closed and a later crash goes to stderr as
any crash does, traceback included. ``end_process`` ends one: signals, a grace period each,
then SIGKILL. No rclpy, no python-can here.
"""
import os
import select
import signal
import subprocess
import sys
import traceback
from typing import Callable, List, Optional, Sequence

#: Set it to 1 for the traceback of a child that fails to start (its one line comes anyway).
TRACEBACK_ENV = 'WHEELLEG_BALANCE_TRACEBACK'
#: The file descriptor a child reports a failed start on (set by ``Child``).
REPORT_FD_ENV = 'WHEELLEG_BALANCE_REPORT_FD'
#: The longest report line read [bytes].
_REPORT_MAX = 4096


class StartError(RuntimeError):
    """A process cannot start: what failed, why, the fix; ``str()`` is the one line."""

    def __init__(self, what: str, why: str = '', fix: str = ''):
        super().__init__(what, why, fix)
        self.what, self.why, self.fix = what, why, fix

    def __str__(self) -> str:
        """Return 'what: why; fix' on one line (a child's line: ``what`` alone)."""
        line = self.what + (': ' + self.why if self.why else '') \
            + ('; ' + self.fix if self.fix else '')
        return ' '.join(line.split())


def package_root() -> str:
    """Return the folder this package was imported from (the parent of wheelleg_balance/)."""
    return os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child_path() -> List[str]:
    """Return the parent's sys.path for a child: the package's folder first, no '' (the cwd)."""
    out: List[str] = []
    for p in [package_root()] + sys.path:
        if p and p not in out:
            out.append(p)
    return out


def child_env(report_fd: Optional[int] = None) -> dict:
    """Return this process's environment for a child: PYTHONPATH = ``child_path()``."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(child_path()))
    env.pop(REPORT_FD_ENV, None)
    if report_fd is not None:
        env[REPORT_FD_ENV] = str(report_fd)
    return env


def child_command(module: str, args: Sequence[str] = ()) -> List[str]:
    """Return the command that runs ``module`` with this interpreter, never from the cwd."""
    return [sys.executable, '-P', '-m', module, *args]


class Child:
    """
    A child process running ``module`` (see the module docstring).

    what: its name in messages ('the control process'); args: its arguments; pass_fds: the
    descriptors it inherits. ``process`` is the Popen.
    """

    def __init__(self, what: str, module: str, args: Sequence[str] = (),
                 pass_fds: Sequence[int] = ()):
        self.what = what
        read, write = os.pipe()
        try:
            self.process = subprocess.Popen(child_command(module, args),
                                            pass_fds=(*pass_fds, write), env=child_env(write))
        except BaseException:
            os.close(read)
            raise
        finally:
            os.close(write)   # the child's copy is the only writer: its exit is our EOF
        self._report: Optional[int] = read

    @property
    def pid(self) -> int:
        """Return the child's process id."""
        return self.process.pid

    def failure(self, wait: float = 0.0) -> Optional[str]:
        """
        Return why it did not start: its line, else once it has ended its exit code; else None.

        wait: how long to wait for either [s]. The line counts as soon as it is written (the
        child may take a while to end after it).
        """
        if self._report is not None and select.select([self._report], [], [], wait)[0]:
            line = os.read(self._report, _REPORT_MAX).decode(errors='replace').strip()
            self.started()   # read once: a line, or the end of a child that wrote none
            if line:
                return line
        try:
            code = self.process.wait(wait)
        except subprocess.TimeoutExpired:
            return None
        return '%s ended while starting (exit code %s)' % (self.what, code)

    def started(self) -> None:
        """Close the report pipe: from now on a failure goes to stderr (idempotent)."""
        if self._report is not None:
            os.close(self._report)
            self._report = None


def _report(line: str) -> None:
    """Give the parent the one line (its pipe; stderr when there is none or it is closed)."""
    fd = os.environ.get(REPORT_FD_ENV)
    if fd:
        try:
            os.write(int(fd), (line + '\n').encode())
            return
        except (OSError, ValueError):
            pass
    print(line, file=sys.stderr, flush=True)


def run_child(what: str, main: Callable[[], int]) -> int:
    """
    Run a child's ``main``; an exception that escapes it is one line and exit code 2.

    A StartError is its own line; any other exception 'what failed: Type: message', with how
    to get the traceback. With ``WHEELLEG_BALANCE_TRACEBACK=1``, or once the parent has closed
    the report pipe (the child had started: a crash, not a failed start), the traceback goes
    to stderr too.
    """
    try:
        return main()
    except Exception as exc:  # noqa: B902 -- one line to the parent, not a traceback
        failed = exc
    if isinstance(failed, StartError):
        line = str(failed)
    else:
        line = str(StartError('%s failed' % what, '%s: %s' % (type(failed).__name__, failed),
                              'set %s=1 for the traceback' % TRACEBACK_ENV))
    if os.environ.get(TRACEBACK_ENV, '') not in ('', '0') \
            or not _pipe_open(os.environ.get(REPORT_FD_ENV)):
        traceback.print_exception(failed)
    _report(line)
    return 2


def _pipe_open(fd: Optional[str]) -> bool:
    """Tell whether the report pipe ``fd`` still has its reader (the parent is starting us)."""
    if not fd:
        return False
    try:
        # A pipe whose reader is gone reports an error condition to poll (POLLERR).
        p = select.poll()
        p.register(int(fd), select.POLLERR)
        return not p.poll(0)
    except (OSError, ValueError):
        return False


def end_process(proc: subprocess.Popen, signum: int = signal.SIGTERM, timeout: float = 2.0,
                then: Sequence[int] = ()) -> None:
    """
    End a running ``proc``: ``signum``, then each of ``then``, each given ``timeout`` [s]; SIGKILL.

    Returns once the process has ended (its exit status is reaped). A node given SIGINT or
    SIGTERM runs its shutdown (zero torque, exit frames); SIGKILL is the last resort for one
    that hangs.
    """
    for sig in (signum, *then):
        if proc.poll() is not None:
            return
        proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
            return
        except subprocess.TimeoutExpired:
            pass
    proc.kill()
    proc.wait()
