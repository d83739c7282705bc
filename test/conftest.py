"""
What the ROS tests share: isolation from other runs and a module-scoped rclpy context.

pytest loads this file before it imports any test module of this folder, so the isolation below
is in place before a test module starts rclpy or a child process. Shared code reaches the tests
as fixtures from here, from the package (polling:
``wheelleg_balance.validation.faults.rig.wait_for``)
or from a helper module of this folder (``nonlinear_model.py``; pytest puts test/ on the path,
and test_packaging.py knows such modules are not dependencies).
"""
import os

import pytest
import rclpy
from rclpy.context import Context


def isolate_ros() -> None:
    """
    Keep this run's ROS traffic to itself: a domain from the pid, localhost discovery only.

    setdefault: a domain the caller exported (scripts/test.sh does) is kept. Child processes
    inherit both variables.
    """
    os.environ.setdefault('ROS_DOMAIN_ID', str(10 + os.getpid() % 90))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'


isolate_ros()


@pytest.fixture(scope='module')
def context():
    """Return an initialized rclpy Context of the test module's own, shut down after it."""
    ctx = Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)


class FaultRetries:
    """The fault suite's scenario runs and reruns in this test run (test/test_faults.py)."""

    def __init__(self):
        self.runs = 0
        self.reruns = []   # (scenario, why)

    def ran(self, name: str) -> None:
        self.runs += 1

    def retried(self, name: str, why: str) -> None:
        self.reruns.append((name, why))


_FAULT_RETRIES = FaultRetries()


@pytest.fixture(scope='session')
def fault_retries() -> FaultRetries:
    """Return the record of the fault suite's reruns, which the closing summary reports."""
    return _FAULT_RETRIES


def pytest_terminal_summary(terminalreporter):
    """Close the run with the count of fault-suite reruns (none when none ran)."""
    r = _FAULT_RETRIES
    if not r.runs:
        return
    terminalreporter.write_sep('=', 'fault suite: %d scenario runs, %d retried'
                               % (r.runs, len(r.reruns)))
    for name, why in r.reruns:
        terminalreporter.write_line('retried %s' % why)
