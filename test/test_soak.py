"""
The soak benchmark (validation/bench/soak.py): its measurements on known series, and a smoke run.

No timing target is asserted (shared machines): the figures are checked on series whose answer
is known by construction, and the smoke run checks that one short soak balances, churns and
reports every figure.
"""
import json
import math
import os
import pathlib
import socket
import subprocess
import sys

import numpy as np
import pytest

from wheelleg_balance.validation.bench import soak
from wheelleg_balance.validation.bench.node import SAFETY_STATUS, udp_drops

REPO = pathlib.Path(__file__).resolve().parents[1]
MS = 1_000_000


# ------------------------------------------------------------------------------ gaps

def test_longest_gap_and_gaps_over_on_a_grid_with_two_holes():
    t = np.arange(1000, dtype=np.int64) * 2 * MS
    # A 330 ms freeze after frame 100 and a 12 ms one after frame 600: the frames in between
    # never came.
    t = np.concatenate([t[:101], t[101:] + 328 * MS])
    t = np.concatenate([t[:601], t[601:] + 10 * MS])
    assert soak.longest_gap_ms(t) == pytest.approx(330.0)
    gaps = soak.gaps_over(t, 10.0)
    assert [(start, round(length, 6)) for start, length in gaps] == [
        (int(t[100]), 330.0), (int(t[600]), 12.0)]
    assert soak.gaps_over(t, 330.0) == []           # strictly longer than the limit
    assert soak.gaps_over(t[:100], 10.0) == []      # the even grid alone


def test_longest_gap_of_too_few_frames_is_nan():
    assert math.isnan(soak.longest_gap_ms([]))
    assert math.isnan(soak.longest_gap_ms([5]))
    assert soak.longest_gap_ms([0, 3 * MS]) == pytest.approx(3.0)


# ------------------------------------------------------------------ counters, windows

def test_counter_delta_starts_from_the_last_sample_before_the_window():
    samples = [(10, 5.0), (20, 7.0), (30, 7.0), (40, 12.0), (50, 20.0)]
    assert soak.counter_delta(samples, 25, 45) == 12.0 - 7.0
    assert soak.counter_delta(samples, 0, 45) == 12.0 - 5.0      # no sample before: first in
    assert soak.counter_delta(samples, 20, 50) == 20.0 - 7.0     # t0 itself counts as before
    assert math.isnan(soak.counter_delta(samples, 51, 60))       # nothing in the window
    assert soak.counter_delta([(10, math.nan), (20, 3.0), (30, 4.0)], 15, 30) == 1.0


def test_window_max_keeps_to_the_window():
    samples = [(10, 400.0), (20, 3.0), (30, 16.5), (40, 2.1), (50, 333.0)]
    assert soak.window_max(samples, 15, 45) == 16.5
    assert soak.window_max(samples, 0, 100) == 400.0
    assert math.isnan(soak.window_max(samples, 41, 49))


class _Log:
    def __init__(self, records):
        self.records = records


def test_first_fault_in_the_window_with_its_time_and_reason():
    t0 = 1_000 * MS
    records = [
        (t0 - 5 * MS, 'hw', SAFETY_STATUS, {'mode': 'FAULT', 'fault_reasons': 'before'}),
        (t0 + 100 * MS, 'other', SAFETY_STATUS, {'mode': 'FAULT', 'fault_reasons': 'not ours'}),
        (t0 + 200 * MS, 'hw', 'balance_node: control loop', {'mode': 'FAULT'}),
        (t0 + 300 * MS, 'hw', SAFETY_STATUS, {'mode': 'BALANCING'}),
        (t0 + 2500 * MS, 'hw', SAFETY_STATUS,
         {'mode': 'FAULT', 'fault_reasons': 'IMU silent for 0.251 s'}),
    ]
    assert soak.first_fault(_Log(records), 'hw', t0, t0 + 3000 * MS) == \
        '2.5 s: IMU silent for 0.251 s'
    assert soak.first_fault(_Log(records), 'hw', t0, t0 + 2000 * MS) == ''


def test_faults_in_log_with_their_times(tmp_path):
    log = tmp_path / 'node.log'
    log.write_text(
        '[INFO] [1796171836.402425776] [ns.balance_node]: balance_node: controller ida_pbc\n'
        '[ERROR] [1796171838.500000000] [ns.balance_node]: FAULT: IMU silent for 0.252 s\n'
        '[WARN] [1796171839.0] [ns.balance_node]: control loop: a tick came 14.0 ms late\n'
        '[ERROR] [1796171841.25] [ns.balance_node]: FAULT: |theta| 64.6 deg\n'
        '[ERROR] [1796171900.000000000] [ns.balance_node]: FAULT: after the window\n')
    t0 = 1796171837 * 1_000_000_000
    faults = soak.faults_in_log(str(log), t0, t0 + 10 * 1_000_000_000)
    assert [(round(t, 3), why) for t, why in faults] == [
        (1.5, 'IMU silent for 0.252 s'), (4.25, '|theta| 64.6 deg')]
    assert soak.faults_in_log(str(tmp_path / 'none.log'), 0, t0) == []


def test_fault_entries_count_each_entry_into_fault_once():
    t0 = 1000
    modes = ['BALANCING', 'FAULT', 'FAULT', 'BALANCING', 'FAULT', 'DISARMED', 'FAULT']
    records = [(t0 + 10 * k, 'hw', SAFETY_STATUS, {'mode': m}) for k, m in enumerate(modes)]
    records.insert(2, (t0 + 15, 'other', SAFETY_STATUS, {'mode': 'BALANCING'}))
    assert soak.fault_entries(_Log(records), 'hw', t0, t0 + 100) == 3
    assert soak.fault_entries(_Log(records), 'hw', t0 + 25, t0 + 100) == 2
    # Already in FAULT when the window opens: no entry.
    assert soak.fault_entries(_Log(records[:4]), 'hw', t0 + 20, t0 + 30) == 0


def test_targets_pass_only_without_gaps_and_skips():
    ok = {'longest_torque_frame_gap_ms': 9.9, 'deadlines_skipped': 0.0}
    assert soak.targets(ok) == {'no torque-frame gap over 10 ms': True,
                                'no deadline skipped': True}
    bad = soak.targets({'longest_torque_frame_gap_ms': 333.6, 'deadlines_skipped': 165.0})
    assert not any(bad.values())
    # No figure (NaN) never passes.
    assert not any(soak.targets({'longest_torque_frame_gap_ms': math.nan,
                                 'deadlines_skipped': math.nan}).values())


def test_churn_summary_counts_cycles_kills_and_answers(tmp_path):
    log = tmp_path / 'churn.jsonl'
    rows = [{'cycle': 1, 'took_s': 1.2, 'ops': {'arm': 'ok 0.5 s', 'param': 'no reply 3.0 s',
                                                'state': 'ok 0.2 s', 'join': 'ok 0.3 s'}},
            {'killed_process': 123, 'ended_before_kill': False},
            {'cycle': 2, 'took_s': 2.5, 'ops': {'arm': 'ok,ok 0.5 s', 'param': 'ok 1.0 s',
                                                'state': 'ok,no message 3.0 s',
                                                'join': 'ok 0.3 s'}}]
    log.write_text(''.join(json.dumps(r) + '\n' for r in rows))
    c = soak.churn_summary(str(log))
    assert (c['cycles'], c['participants'], c['killed_processes']) == (2, 8, 1)
    assert c['cycle_time_max_s'] == 2.5
    assert c['ops_answered'] == {'arm': 2, 'param': 1, 'state': 1, 'join': 2}
    assert soak.churn_summary(str(tmp_path / 'none.jsonl'))['cycles'] == 0


# --------------------------------------------------------------------- recorder drops

def test_udp_drops_counts_what_the_kernel_dropped():
    # A socket with the smallest receive buffer that nobody reads: the kernel drops the excess,
    # which is what would fake gaps in a recording.
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1)
        rx.bind(('127.0.0.1', 0))
        inode = os.fstat(rx.fileno()).st_ino
        assert udp_drops(inode) == 0
        for _ in range(200):
            tx.sendto(b'x' * 1000, rx.getsockname())
        assert udp_drops(inode) > 0
    finally:
        rx.close()
        tx.close()
    assert udp_drops(None) == -1
    assert udp_drops(inode) == -1   # closed: not found


# ------------------------------------------------------------------------ smoke run

@pytest.mark.ros
@pytest.mark.slow   # 25 to 50 s on a shared 2-core machine: node start-up, 5 s warm-up, 3 s
def test_smoke_run(tmp_path):
    out = tmp_path / 'soak.json'
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (str(REPO), env.get('PYTHONPATH')) if p)
    proc = subprocess.run(
        [sys.executable, '-m', 'wheelleg_balance.validation.bench.soak', '--duration', '3',
         '--churn-period', '1', '--kill-every', '2', '--plant-priority', '0',
         '--output', str(out), '--workdir', str(tmp_path / 'raw')],
        env=env, capture_output=True, text=True, timeout=180, cwd=str(tmp_path))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    report = json.loads(out.read_text())
    node = report['node']
    assert 'baseline' not in report and report['errors'] == {}
    assert node['window_s'] == pytest.approx(3.0, abs=1.0)
    assert node['churn']['cycles'] >= 1
    figures = node['soak']
    # The node commanded the motors through the window and the bus recorded every frame. On a
    # loaded machine it may fault (a sensor starved): then the report must say so; without a
    # fault nearly every wheel frame carries the probes' torque.
    assert node['motors']['1']['frames'] > 0
    assert figures['recorder_receive_drops'] == 0
    assert figures['faults'] > 0 or figures['balancing_share'] > 0.5, figures
    for key in ('longest_torque_frame_gap_ms', 'longest_tick_gap_ms', 'deadlines_skipped',
                'sensor_rate_hz'):
        assert figures[key] is not None and figures[key] >= 0, key
    assert set(node['targets']) == {'no torque-frame gap over 10 ms', 'no deadline skipped'}
    assert 'longest torque-frame gap' in proc.stdout
