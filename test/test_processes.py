"""end_process: the signal first, SIGKILL only for a child that does not end in time."""
import signal
import subprocess
import sys
import time

from wheelleg_balance.processes import end_process


def _child(code: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, '-c', code + '\nprint("ready", flush=True)\n'
                             'import time\nwhile True: time.sleep(0.05)'],
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == 'ready'
    return proc


def test_a_child_that_obeys_ends_by_the_signal():
    # Python's own SIGINT handling, even where the test runs with SIGINT ignored (a shell's
    # background job without job control passes SIG_IGN on, and Python then keeps it).
    proc = _child('import signal\nsignal.signal(signal.SIGINT, signal.default_int_handler)')
    end_process(proc, signal.SIGINT, 5.0)
    assert proc.returncode == -signal.SIGINT   # ended by the signal itself, not SIGKILL


def test_a_child_that_ignores_the_signal_is_killed_after_the_timeout():
    proc = _child('import signal\nsignal.signal(signal.SIGTERM, signal.SIG_IGN)')
    t0 = time.monotonic()
    end_process(proc, signal.SIGTERM, 0.3)
    assert proc.returncode == -signal.SIGKILL
    assert time.monotonic() - t0 >= 0.3


def test_an_ended_child_is_left_alone():
    proc = subprocess.Popen([sys.executable, '-c', 'pass'])
    proc.wait()
    end_process(proc)
    assert proc.returncode == 0


def test_the_signals_escalate_in_turn_before_sigkill():
    proc = _child('import signal\nsignal.signal(signal.SIGINT, signal.SIG_IGN)')
    end_process(proc, signal.SIGINT, 0.3, then=(signal.SIGTERM,))
    assert proc.returncode == -signal.SIGTERM   # SIGINT ignored, SIGTERM ended it
