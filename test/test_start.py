"""
balance_node's start: what each process imports, and the start part's figures (bench/start.py).

Timing is the benchmark's (``benchmark --parts start``, docs/benchmarks.md "Start-up"), never a
test's: these machines are shared. Here: the processes import only what they use (the watchdog
no numpy, nothing scipy unless a height table must be solved; the ROS shell no python-can), and
the start part's parsing and arithmetic on inputs whose answer is known.
"""
import os
import pathlib
import subprocess
import sys
import textwrap

import pytest

from wheelleg_balance.core import default_tables, table_cache
from wheelleg_balance.validation.bench import start

REPO = pathlib.Path(__file__).resolve().parents[1]


def _modules_after(code: str, env=None) -> set:
    """Run ``code`` in a fresh interpreter on this package; return the modules it imported."""
    script = code + '\nimport sys\nprint(" ".join(sorted(sys.modules)))\n'
    env = dict(os.environ if env is None else env)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    out = subprocess.run([sys.executable, '-P', '-c', script], env=env, capture_output=True,
                         text=True, timeout=120, check=True).stdout.split()
    return set(out)


def _top(modules: set) -> set:
    return {m.split('.')[0] for m in modules}


# ------------------------------------------------------------------------------ imports

def test_the_watchdog_starts_on_python_can_alone():
    """Its main's imports (it stops at --help): no numpy, no scipy, no rclpy, no control core."""
    mods = _modules_after(textwrap.dedent("""
        import wheelleg_balance.nodes.watchdog as w
        try:
            w.main(['--help'])
        except SystemExit:
            pass"""))
    assert 'can' in _top(mods)
    assert not _top(mods) & {'numpy', 'scipy', 'rclpy'}
    assert not {'wheelleg_balance.core.config', 'wheelleg_balance.core.balance_loop'} & mods


def test_the_watchdog_plan_carries_the_stop_frames_of_every_motor():
    from wheelleg_balance.core.balance_loop import all_stop_frames
    from wheelleg_balance.core.config import BalanceConfig
    from wheelleg_balance.core.schema import to_flat, with_changes
    from wheelleg_balance.nodes import watchdog
    for changes, buses in (({}, 1), ({'legs.driven': True}, 1),
                           ({'legs.driven': True, 'legs.can.channel': 'can1'}, 2)):
        cfg = with_changes(BalanceConfig(), changes)
        plan = watchdog.plan(to_flat(cfg))
        wheels, legs = all_stop_frames(cfg)
        frames = [f for _, fs in plan['buses'] for f in fs]
        assert len(plan['buses']) == buses
        assert frames == [[f.arbitration_id, f.data.hex(), f.is_extended_id]
                          for f in wheels + legs]
        assert plan['limit'] == watchdog.stall_limit(cfg)
        assert plan['interface'] == cfg.can.interface


def test_the_sensor_intake_needs_no_scipy():
    mods = _modules_after(textwrap.dedent("""
        import wheelleg_balance.nodes.sensor_intake as s
        try:
            s.main(['--help'])
        except SystemExit:
            pass"""))
    assert 'rclpy' in _top(mods) and 'scipy' not in _top(mods)


def test_the_ros_shell_imports_neither_scipy_nor_python_can():
    mods = _modules_after('import wheelleg_balance.nodes.balance_node')
    assert 'rclpy' in _top(mods)
    assert not _top(mods) & {'scipy', 'can'}


def test_the_control_loop_with_its_tables_found_solves_nothing(tmp_path):
    """The default loop's tables in the cache folder: scipy's solvers are never imported."""
    default_tables.write_defaults(str(tmp_path))
    env = dict(os.environ, **{table_cache.CACHE_ENV: str(tmp_path)})
    mods = _modules_after(textwrap.dedent("""
        import wheelleg_balance.nodes.control_process
        from wheelleg_balance.core import table_cache
        from wheelleg_balance.core.balance_loop import BalanceLoop
        from wheelleg_balance.core.config import BalanceConfig
        table_cache.keep_in(table_cache.default_folder())
        BalanceLoop(BalanceConfig())"""), env)
    assert not {'scipy.signal', 'scipy.linalg', 'sympy', 'matplotlib', 'rclpy'} & mods


# ------------------------------------------------------------------- the start part

STAMPED = '[INFO] [1796662465.751621391] [ns.balance_node]: balance_node: controller auto, ' \
    'CAN udp_multicast:239.74.163.51 (mit, motors 1/2), 2.0 ms loop in its own process\n'


def test_the_ready_line_and_its_stamp():
    assert start.ready_stamp(STAMPED) == pytest.approx(1796662465.751621391, abs=1e-6)
    assert start.ready_stamp('[INFO] [1796662465.7] [ns.balance_node]: sensor intake ready\n') \
        is None
    no_stamp = start.ready_stamp('balance_node: controller lqr, CAN virtual:x\n')
    assert no_stamp != no_stamp   # NaN: the time the line was read stands in


def test_the_starts_take_turns_and_each_tree_runs_every_round():
    assert start.run_order(3, 1) == [0, 0, 0]
    assert start.run_order(3, 2) == [0, 1, 1, 0, 0, 1]
    assert start.run_order(2, 3) == [0, 1, 2, 1, 2, 0]
    order = start.run_order(5, 3)
    assert [order.count(k) for k in range(3)] == [5, 5, 5]


def test_the_summary_is_the_median_of_the_starts():
    starts = [{'ready_s': t, 'cpu_s': {'ros_shell': c, 'watchdog': 0.1}}
              for t, c in ((1.0, 0.5), (3.0, 0.4), (2.0, 0.7), (9.0, 0.6), (1.5, 0.3))]
    s = start.summary(starts)
    assert (s['n'], s['median_s'], s['min_s'], s['max_s']) == (5, 2.0, 1.0, 9.0)
    assert s['cpu_median_s'] == {'ros_shell': 0.5, 'watchdog': 0.1}
    assert s['cpu_total_median_s'] == pytest.approx(0.6)
    assert start.summary(starts[:4])['median_s'] == 2.5   # an even count: the middle two
    report = {'trees': [dict(label='this tree', **s)]}
    assert start.targets(report)[0]['pass'] is True       # 2.0 s: the limit itself passes
    report['trees'][0]['median_s'] = start.TARGET_S + 0.001
    assert start.targets(report)[0]['pass'] is False


def test_a_tree_starts_by_its_installed_executable_else_by_its_source(tmp_path):
    env = {'PYTHONPATH': '/elsewhere', 'AMENT_PREFIX_PATH': '/opt/ros'}
    source = start.tree_command(str(tmp_path), env)
    assert source.command[-2:] == ['-m', 'wheelleg_balance.nodes.balance_node']
    assert source.env['PYTHONPATH'] == os.pathsep.join((str(tmp_path), '/elsewhere'))
    prefix = tmp_path / '.colcon' / 'install' / 'wheelleg_balance'
    site = prefix / 'lib' / ('python%d.%d' % sys.version_info[:2]) / 'site-packages'
    site.mkdir(parents=True)
    exe = prefix / 'lib' / 'wheelleg_balance' / 'balance_node'
    exe.parent.mkdir(parents=True)
    exe.write_text('#!/bin/sh\n')
    installed = start.tree_command(str(tmp_path), env)
    assert installed.command == [str(exe)]
    assert installed.env['PYTHONPATH'].split(os.pathsep)[0] == str(site)
    assert installed.env['AMENT_PREFIX_PATH'].split(os.pathsep)[0] == str(prefix)
    assert start.install_of(str(site)) == str(prefix)
    assert start.install_of(str(tmp_path)) is None


def _fake_node(tmp_path, body: str) -> start.NodeCommand:
    script = tmp_path / 'node.py'
    script.write_text(textwrap.dedent(body))
    return start.NodeCommand('fake', [sys.executable, str(script)], dict(os.environ), 'fake')


def test_a_start_is_timed_to_its_ready_lines_stamp_and_then_stopped(tmp_path, monkeypatch):
    node = _fake_node(tmp_path, """
        import signal, sys, time
        signal.signal(signal.SIGINT, lambda *a: sys.exit(0))
        print('[WARN] [1000.100000000] [n]: tf2_msgs is not installed', flush=True)
        print('[INFO] [1001.250000000] [n]: balance_node: controller auto, CAN x', flush=True)
        time.sleep(60)""")
    monkeypatch.setattr(start.time, 'time', lambda: 1000.0)   # the start's wall clock
    result = start.time_start(node, [], timeout=30.0)
    assert result['ready_s'] == pytest.approx(1.25, abs=1e-9)
    assert result['seen_s'] > 0.0 and 'ros_shell' in result['cpu_s']


def test_a_start_that_ends_without_its_ready_line_fails_with_its_output(tmp_path):
    node = _fake_node(tmp_path, """
        print('balance_node: the control process: no bus', flush=True)""")
    with pytest.raises(RuntimeError, match='no bus'):
        start.time_start(node, [], timeout=30.0)
