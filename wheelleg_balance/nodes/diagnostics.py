"""
balance_node's /diagnostics from the control loop's status (nodes/control_process.py).

Three statuses, each with its values (docs/interface.md): ``balance_node: safety`` (mode,
faults, why it cannot arm, the controller, the references), ``balance_node: control loop``
(periods, compute times, skipped and late deadlines, stalls, whether the loop is alive) and
``balance_node: CAN`` (frame and error counters, per motor: alive, reply age, feedback).
"""
import math
from typing import Any, Dict, List, Optional

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


def key_values(**values) -> List[KeyValue]:
    """Return a KeyValue list, floats as %.6g."""
    return [KeyValue(key=k, value='%.6g' % v if isinstance(v, float) else str(v))
            for k, v in values.items()]


def _reasons(pairs) -> str:
    return '; '.join(message for _, message in pairs)


def safety_status(st: Dict[str, Any], hardware_id: str) -> DiagnosticStatus:
    """Build the supervisor's status: mode and reasons."""
    out = DiagnosticStatus(name='balance_node: safety', hardware_id=hardware_id)
    mode, faults, conditions = st['mode'], st['faults'], st['conditions']
    if mode == 'FAULT':
        out.level, out.message = ERROR, 'FAULT: ' + _reasons(faults)
    elif mode == 'BALANCING':
        out.level, out.message = OK, 'BALANCING with %s' % st['controller']
    elif mode == 'EXCITING':
        out.level, out.message = OK, 'EXCITING'
    else:
        out.level = WARN if conditions else OK
        out.message = 'DISARMED' + (' (cannot arm: %s)' % _reasons(conditions)
                                    if conditions else '')
    phase = st.get('excitation', 'none')
    if phase != 'none':   # an identification phase (core/excitation.py)
        out.message += '; identification %s %.0f %%%s' % (
            phase, 100.0 * st['excitation_progress'],
            ' (probing the wheels)' if st['excitation_probing'] else '')
    if st['input_conflicts']:   # inputs refused for their publishers (nodes/input_guard.py)
        out.level = max(out.level, WARN)
        out.message += '; refused: %s' % st['input_conflicts']
    foreign, warnings = st.get('foreign_command_reason', ''), st.get('warnings', [])
    if foreign:   # command frames of another sender to our motors (core/balance_loop.py)
        out.level = max(out.level, WARN)
        out.message += '; %s' % foreign
    if warnings:   # WARNING_CODES (core/safety.py): no FAULT, but not right either
        out.level = max(out.level, WARN)
        out.message += ''.join('; %s: %s' % w for w in warnings)
    out.values = key_values(
        mode=mode, mode_index=st['mode_index'], faults=','.join(c for c, _ in faults),
        fault_reasons=_reasons(faults), conditions=','.join(c for c, _ in conditions),
        controller=st['controller'], controller_parameter=st['controller_parameter'],
        x_dot_ref=st['x_dot_ref'], yaw_rate_ref=st['yaw_rate_ref'],
        cmd_vel_timed_out=st['cmd_vel_timed_out'], rejected_cmd_vel=st['rejected_cmd_vel'],
        frozen_imu_samples=st['frozen_imu_samples'],
        refused_imu_stamps=st['refused_imu_stamps'],
        refused_imu_reason=st['refused_imu_reason'], input_conflicts=st['input_conflicts'],
        foreign_commands=st.get('foreign_commands', 0), foreign_command_reason=foreign,
        warnings=','.join(c for c, _ in warnings), warning_reasons=_reasons(warnings),
        excitation=phase, excitation_progress=float(st.get('excitation_progress', 0.0)))
    return out


def loop_status(st: Dict[str, Any], hardware_id: str, age: float,
                alive_limit: float) -> DiagnosticStatus:
    """Build the control loop's status; ERROR when its status is older than ``alive_limit`` [s]."""
    t = st['timing']
    out = DiagnosticStatus(name='balance_node: control loop', hardware_id=hardware_id)
    alive = age <= alive_limit
    if not alive:
        out.level = ERROR
        out.message = 'control loop silent for %.3f s' % age
    else:
        out.level = OK if t['late_share'] < 0.05 and not t['tick_errors'] else WARN
        out.message = ('period mean %.3f ms, p99 %.3f ms, max %.3f ms, %d deadlines skipped, '
                       '%d caught up, %d stalls' % (
                           1e3 * t['period_mean'], 1e3 * t['period_p99'],
                           1e3 * t['period_max'], t['overruns'], t['caught_up'], t['stalls']))
    out.values = key_values(
        alive=alive, status_age_s=age, period_target_ms=1e3 * st['period_target'],
        period_mean_ms=1e3 * t['period_mean'], period_p99_ms=1e3 * t['period_p99'],
        period_max_ms=1e3 * t['period_max'], overruns=t['overruns'],
        caught_up=t['caught_up'], late_share=t['late_share'], ticks=t['ticks'],
        stalls=t['stalls'], longest_stall_ms=1e3 * t['longest_stall'],
        compute_mean_ms=1e3 * t['compute_mean'], compute_p99_ms=1e3 * t['compute_p99'],
        compute_max_ms=1e3 * t['compute_max'], compute_budget_ms=1e3 * t['budget'],
        over_budget=t['over_budget'], core_compute_mean_ms=1e3 * t['core_mean'],
        core_compute_p99_ms=1e3 * t['core_p99'], core_compute_max_ms=1e3 * t['core_max'],
        tick_errors=t['tick_errors'],
        link_dropped=st['link_dropped'], realtime=st['realtime'])
    return out


#: Bus load [%] above which the CAN status warns (replies start to come late, docs/legs.md).
BUS_LOAD_WARN = 90.0


def _pct(value: Optional[float]) -> float:
    """Return a load [%] for key_values (NaN until a second status has measured it)."""
    return math.nan if value is None else round(value, 1)


def can_status(st: Dict[str, Any], hardware_id: str) -> DiagnosticStatus:
    """Bus counters and per-motor liveness and feedback."""
    io = st['can']
    out = DiagnosticStatus(name='balance_node: CAN', hardware_id=hardware_id)
    values = {'protocol': st['protocol'], 'tx_frames': io['tx_frames'],
              'tx_errors': io['tx_errors'], 'last_tx_error': io['last_tx_error'],
              'rx_frames': io['rx_frames'], 'rx_replies': st['rx_replies'],
              'rx_errors': io['rx_errors'], 'last_rx_error': io['last_rx_error'],
              'rx_echoes': io.get('rx_echoes', 0),
              'bus_load_pct': _pct(io.get('load_pct')),
              'max_catch_up': st.get('max_catch_up', math.nan)}
    legs = st.get('leg_can')
    if legs is not None:  # the hips on a bus of their own
        values.update({'leg_bus_tx_frames': legs['tx_frames'],
                       'leg_bus_tx_errors': legs['tx_errors'],
                       'leg_bus_rx_frames': legs['rx_frames'],
                       'leg_bus_load_pct': _pct(legs.get('load_pct'))})
    all_alive = True
    for motor_id, m in st['motors'].items():
        all_alive = all_alive and m['alive']
        prefix = 'motor_%d_' % motor_id
        values[prefix + 'alive'] = m['alive']
        values[prefix + 'reply_age_s'] = m['reply_age_s']
        values[prefix + 'replies'] = m['replies']
        fb = m['feedback']
        if fb is not None:
            _, position, velocity, torque, temperature, error = fb[:6]
            values.update({prefix + 'position': position, prefix + 'velocity': velocity,
                           prefix + 'torque': torque, prefix + 'temperature': temperature,
                           prefix + 'error': error})
    out.values = key_values(**values)
    if st['mode'] != 'DISARMED' and not all_alive:
        out.level, out.message = ERROR, 'motor not answering'
    elif io['tx_errors']:
        out.level = WARN
        out.message = '%d send errors, last: %s' % (io['tx_errors'], io['last_tx_error'])
    elif max(values['bus_load_pct'], values.get('leg_bus_load_pct', 0.0)) > BUS_LOAD_WARN:
        out.level = WARN   # NaN compares false: no warning before the first figure
        out.message = 'bus load %.0f %% (legs: %.0f %%): above %.0f %%' % (
            values['bus_load_pct'], values.get('leg_bus_load_pct', math.nan), BUS_LOAD_WARN)
    else:
        out.level, out.message = OK, 'ok'
    return out


def watchdog_status(wd: Dict[str, Any], hardware_id: str) -> DiagnosticStatus:
    """Build the watchdog's status (nodes/watchdog.py): ERROR once it fired or when it is gone."""
    out = DiagnosticStatus(name='balance_node: watchdog', hardware_id=hardware_id)
    if wd['fired']:
        out.level = ERROR
        out.message = ('%s (heartbeat %.0f ms old, limit %.0f ms): zero torque and exit sent, '
                       'control process ended; restart balance_node'
                       % (wd['text'], 1e3 * wd['stall'], 1e3 * wd['timeout']))
    elif not wd['running']:
        out.level, out.message = ERROR, 'watchdog not running (%s)' % wd['text']
    else:
        out.level, out.message = OK, '%s, limit %.0f ms' % (wd['text'], 1e3 * wd['timeout'])
    out.values = key_values(state=wd['text'], fired=wd['fired'], running=wd['running'],
                            heartbeat_age_at_fire_ms=1e3 * wd['stall'],
                            timeout_ms=1e3 * wd['timeout'])
    return out


def diagnostic_array(st: Optional[Dict[str, Any]], hardware_id: str, now: float,
                     alive_limit: float, stamp,
                     watchdog: Optional[Dict[str, Any]] = None) -> DiagnosticArray:
    """
    Build the whole DiagnosticArray; without any status yet, one ERROR 'no control loop'.

    watchdog: its state (nodes/watchdog.py WatchdogProcess.state), None without one.
    """
    msg = DiagnosticArray()
    msg.header.stamp = stamp
    extra = [] if watchdog is None else [watchdog_status(watchdog, hardware_id)]
    if st is None:
        msg.status = [DiagnosticStatus(level=ERROR, name='balance_node: control loop',
                                       hardware_id=hardware_id,
                                       message='control loop not running')] + extra
        return msg
    age = now - st['time'] if math.isfinite(st['time']) else math.inf
    msg.status = [safety_status(st, hardware_id), loop_status(st, hardware_id, age,
                                                              alive_limit),
                  can_status(st, hardware_id)] + extra
    return msg
