"""Ending a child process: signals, a grace period each, then SIGKILL (no rclpy, no python-can)."""
import signal
import subprocess
from typing import Sequence


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
