"""
balance_node's children: ended by signals (SIGKILL last), started on the parent's package.

end_process: the signal first, SIGKILL only for a child that does not end in time. Child and
run_child: a failed start is one line to the parent, its traceback only when asked for.
"""
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

from wheelleg_balance import processes
from wheelleg_balance.processes import (Child, child_command, child_env, child_path, end_process,
                                        TRACEBACK_ENV)


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


# ------------------------------------------------------- Child, run_child: a failed start

_CHILD = """
import sys
import time
from wheelleg_balance.processes import run_child, StartError


def main():
    mode = sys.argv[1]
    if mode == 'start_error':
        raise StartError('the thing', 'no bus', 'plug it in')
    if mode == 'late':
        time.sleep(1.0)   # the parent has seen it start by then
    raise KeyError(mode)


sys.exit(run_child('the thing', main))
"""


@pytest.fixture
def child_module(tmp_path, monkeypatch):
    """Return the name of a module that fails as its argument says, on the children's path."""
    name = 'wlb_child_%d' % os.getpid()
    (tmp_path / ('%s.py' % name)).write_text(_CHILD)
    monkeypatch.syspath_prepend(str(tmp_path))   # processes.child_path() passes sys.path on
    monkeypatch.delenv(TRACEBACK_ENV, raising=False)
    return name


def _ended(child: Child) -> str:
    assert child.process.wait(10.0) == 2
    return child.failure()


def test_a_child_that_fails_to_start_gives_its_parent_one_line_and_no_traceback(
        child_module, capfd):
    line = _ended(Child('the thing', child_module, ['start_error']))
    assert line == 'the thing: no bus; plug it in'
    line = _ended(Child('the thing', child_module, ['bug']))
    assert line == ("the thing failed: KeyError: 'bug'; set %s=1 for the traceback"
                    % TRACEBACK_ENV)
    assert capfd.readouterr().err == ''   # nothing on the terminal: the parent says it


def test_the_traceback_of_a_failed_start_comes_when_asked_for(child_module, capfd, monkeypatch):
    monkeypatch.setenv(TRACEBACK_ENV, '1')
    line = _ended(Child('the thing', child_module, ['bug']))
    assert line.startswith("the thing failed: KeyError: 'bug'")
    err = capfd.readouterr().err
    assert 'Traceback' in err and "KeyError: 'bug'" in err


def test_a_crash_after_the_start_goes_to_stderr_with_its_traceback(child_module, capfd):
    child = Child('the thing', child_module, ['late'])
    child.started()   # as balance_node once its start is done
    assert child.process.wait(10.0) == 2
    err = capfd.readouterr().err
    assert 'Traceback' in err and "the thing failed: KeyError: 'late'" in err


def test_a_child_imports_the_parents_package_first_and_never_the_working_directory():
    path = child_path()
    assert path[0] == str(pathlib.Path(processes.__file__).resolve().parent.parent)
    assert '' not in path
    assert child_command('m')[1:] == ['-P', '-m', 'm']
    assert child_env()['PYTHONPATH'].split(os.pathsep) == path
