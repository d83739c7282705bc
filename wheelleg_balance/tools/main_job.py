"""
main_job: balance_node against the simulated robot (sim_node), as separate processes.

Each experiment starts sim_node and balance_node with ``python -m ... --ros-args --params-file``
(parameter files written into the experiment's folder), talking over ROS 2 (this machine only)
and CAN over python-can's udp_multicast interface, exactly as on the robot apart from the bus.
This process records sim_node's ``~/ground_truth`` and balance_node's ``~/state``, arms the
robot through ``balance_node/arm``, switches controllers with a parameter call, and writes per
experiment a CSV of the recordings, a plot and the node logs, then ``report.md`` with the
figures and a verdict. Exit code 0 when every experiment met its criteria.

Experiments (the paper's Sec. V-B; ``--only`` picks some):

- startup: start-up from the tail (about 36 deg) at the lowest height with IDA-PBC (13);
- startup_lqr: the same with the linear controller u = k_x xi~ (the paper's comparison);
- standing: start-up, then output regulation with the observer of the IMU offset d: the robot
  must stand still and d_hat must match the measured equilibrium pitch;
- push: standing with IDA-PBC, kicked forward then backward on the body (experiment 7);
- height: IDA-PBC while the legs go 0.37 -> 0.70 -> 0.37 m (experiment 3, standing in place).
"""
import argparse
import csv
import math
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time
from typing import Dict, List, Optional

from rcl_interfaces.srv import SetParameters
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from std_msgs.msg import Float64MultiArray
from std_srvs.srv import SetBool
import yaml

CAN_GROUP = '239.74.163.2'
IMU_OFFSET = math.radians(2.2)     # d of the simulated IMU, as the paper's robot
MODE_BALANCING = 1
CONTROLLERS = ('ida_pbc', 'output_regulation', 'lqr')


class Experiment:
    """One run: parameters of both nodes, a timeline of actions, and the criteria."""

    def __init__(self, name: str, title: str, duration: float, controller: str = 'ida_pbc',
                 sim: Optional[dict] = None, switch: Optional[tuple] = None):
        self.name = name
        self.title = title
        self.duration = duration        # recorded time after arming [s]
        self.controller = controller    # controller at arm
        self.sim = sim or {}
        self.switch = switch            # (t after arm [s], controller)


# Sim pushes and height schedules run on sim time, which starts with the sim process: the robot
# is armed at ARM_AT s of sim time (room for DDS discovery); scenario times add ARM_AT.
ARM_AT = 4.0

EXPERIMENTS = [
    Experiment('startup', 'Start-up from the tail, IDA-PBC (13)', 6.0),
    Experiment('startup_lqr', 'Start-up from the tail, linear u = k_x xi~', 6.0,
               controller='lqr'),
    Experiment('standing', 'Standing still: output regulation with the d observer', 14.0,
               switch=(4.0, 'output_regulation')),
    Experiment('push', 'Kicks on the body (60 N for 0.1 s, forward then back), IDA-PBC', 12.0,
               sim={'pushes': [ARM_AT + 5.0, 0.1, 60.0, 0.0, ARM_AT + 9.0, 0.1, -60.0, 0.0]}),
    Experiment('height', 'Height 0.37 -> 0.70 -> 0.37 m while balancing, IDA-PBC', 14.0,
               sim={'height_schedule': [ARM_AT + 4.0, 0.37, ARM_AT + 7.0, 0.70,
                                        ARM_AT + 9.0, 0.70, ARM_AT + 12.0, 0.37]}),
]


def _nested(flat: Dict[str, object]) -> dict:
    """{'can.interface': x} -> {'can': {'interface': x}} for a ROS 2 parameter file."""
    out: dict = {}
    for key, value in flat.items():
        parts = key.split('.')
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def _write_params(path: pathlib.Path, node: str, flat: Dict[str, object]) -> None:
    path.write_text(yaml.safe_dump({node: {'ros__parameters': _nested(flat)}},
                                   default_flow_style=None, sort_keys=True))


def balance_params(udp_port: int, controller: str) -> Dict[str, object]:
    """balance_node parameters for the simulated robot (the rest are its defaults)."""
    return {
        'controller': controller,
        'can.interface': 'udp_multicast', 'can.channel': CAN_GROUP, 'can.udp_port': udp_port,
        'can.left_direction': 1, 'can.right_direction': -1,
        # joint_states carries each wheel in its motor's convention (docs/simulation.md).
        'left_wheel_direction': 1, 'right_wheel_direction': -1,
        'left_leg_front_joint': 'left_leg_front_joint',
        'left_leg_rear_joint': 'left_leg_rear_joint',
        'right_leg_front_joint': 'right_leg_front_joint',
        'right_leg_rear_joint': 'right_leg_rear_joint',
        'leg_joint_directions': [1, 1, 1, 1], 'leg_joint_offsets': [0.0, 0.0, 0.0, 0.0],
        'state_publish_rate': 100.0,
    }


def sim_params(udp_port: int, extra: dict) -> Dict[str, object]:
    """sim_node parameters: the robot resting on its tail, IMU offset d, the scenario."""
    flat = {
        'can.interface': 'udp_multicast', 'can.channel': CAN_GROUP, 'can.udp_port': udp_port,
        'can.left_direction': 1, 'can.right_direction': -1,
        'imu_pitch_offset': IMU_OFFSET, 'initial_pose': 'tail', 'ground_truth_rate': 100.0,
    }
    flat.update(extra)
    return flat


class Recorder:
    """This process's ROS side: recordings, the arm service and the parameter client."""

    def __init__(self):
        self.node = rclpy.create_node('main_job')
        self.gt: List[tuple] = []      # (receipt time, data...)
        self.state: List[tuple] = []
        self.gt_labels: List[str] = []
        self.state_labels: List[str] = []
        self.node.create_subscription(Float64MultiArray, 'sim_node/ground_truth',
                                      self._on_gt, 100)
        self.node.create_subscription(Float64MultiArray, 'balance_node/state',
                                      self._on_state, 100)
        self.arm_client = self.node.create_client(SetBool, 'balance_node/arm')
        self.param_client = self.node.create_client(SetParameters,
                                                    'balance_node/set_parameters')
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self.executor.spin, daemon=True)
        self._thread.start()

    def _on_gt(self, msg):
        self.gt_labels = msg.layout.dim[0].label.split(',') if msg.layout.dim else []
        self.gt.append((time.monotonic(),) + tuple(msg.data))

    def _on_state(self, msg):
        self.state_labels = msg.layout.dim[0].label.split(',') if msg.layout.dim else []
        self.state.append((time.monotonic(),) + tuple(msg.data))

    def clear(self):
        self.gt, self.state = [], []

    def call(self, client, request, timeout=3.0):
        """Call a service; the response or None."""
        if not client.wait_for_service(timeout_sec=timeout):
            return None
        future = client.call_async(request)
        end = time.monotonic() + timeout
        while not future.done() and time.monotonic() < end:
            time.sleep(0.01)
        return future.result() if future.done() else None

    def arm(self, on: bool):
        return self.call(self.arm_client, SetBool.Request(data=on))

    def set_controller(self, name: str):
        req = SetParameters.Request()
        req.parameters = [Parameter('controller', value=name).to_parameter_msg()]
        return self.call(self.param_client, req)

    def close(self):
        self.executor.shutdown()
        self.node.destroy_node()


def _start(module: str, params: pathlib.Path, log: pathlib.Path) -> subprocess.Popen:
    out = open(log, 'w')
    return subprocess.Popen([sys.executable, '-m', module, '--ros-args', '--params-file',
                             str(params)], stdout=out, stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _column(rows, labels, name):
    i = labels.index(name) + 1
    return [r[i] for r in rows]


def run_experiment(exp: Experiment, rec: Recorder, folder: pathlib.Path, udp_port: int) -> dict:
    """Run one experiment and return its metrics (see ``evaluate``)."""
    folder.mkdir(parents=True, exist_ok=True)
    _write_params(folder / 'sim.yaml', 'sim_node', sim_params(udp_port, exp.sim))
    _write_params(folder / 'balance.yaml', 'balance_node',
                  balance_params(udp_port, exp.controller))
    rec.clear()
    sim = _start('wheelleg_balance.nodes.sim_node', folder / 'sim.yaml', folder / 'sim_node.log')
    bal = _start('wheelleg_balance.nodes.balance_node', folder / 'balance.yaml',
                 folder / 'balance_node.log')
    notes = []
    t_arm = None
    try:
        # Wait for both nodes, then arm at ARM_AT s of sim time.
        end = time.monotonic() + 30.0
        while time.monotonic() < end:
            if rec.gt and rec.state and rec.gt_labels and \
                    rec.gt[-1][1 + rec.gt_labels.index('time')] >= ARM_AT:
                break
            if sim.poll() is not None or bal.poll() is not None:
                break
            time.sleep(0.01)
        else:
            notes.append('nodes did not come up within 30 s')
        if not notes and sim.poll() is None and bal.poll() is None:
            # balance_node refuses to arm until it has fresh samples of every sensor.
            give_up = time.monotonic() + 10.0
            while True:
                resp = rec.arm(True)
                if (resp is not None and resp.success) or time.monotonic() > give_up:
                    break
                time.sleep(0.2)
            t_arm = time.monotonic()
            if resp is None or not resp.success:
                notes.append('arm refused: %s' % (resp.message if resp else 'no answer'))
            sim_time = rec.gt[-1][1 + rec.gt_labels.index('time')]
            if sim_time > ARM_AT + 1.0:
                notes.append('armed late, at %.1f s of sim time (scenario times assume %.1f)'
                             % (sim_time, ARM_AT))
            switched = exp.switch is None
            while time.monotonic() < t_arm + exp.duration:
                if not switched and time.monotonic() >= t_arm + exp.switch[0]:
                    r = rec.set_controller(exp.switch[1])
                    if r is None or not r.results[0].successful:
                        notes.append('controller switch to %s failed' % exp.switch[1])
                    switched = True
                if sim.poll() is not None or bal.poll() is not None:
                    notes.append('a node exited during the run')
                    break
                time.sleep(0.02)
            rec.arm(False)
    finally:
        _stop(bal)
        _stop(sim)
    if sim.returncode not in (0, -signal.SIGINT, None) or \
            bal.returncode not in (0, -signal.SIGINT, None):
        notes.append('exit codes sim_node %s, balance_node %s'
                     % (sim.returncode, bal.returncode))
    _save_csv(folder / 'ground_truth.csv', rec.gt, rec.gt_labels)
    _save_csv(folder / 'state.csv', rec.state, rec.state_labels)
    metrics = evaluate(exp, rec, t_arm, notes)
    plot(exp, rec, t_arm, folder / ('%s.png' % exp.name))
    return metrics


def _save_csv(path, rows, labels):
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(['receipt_time'] + list(labels))
        w.writerows(rows)


def evaluate(exp: Experiment, rec: Recorder, t_arm: Optional[float], notes: List[str]) -> dict:
    """
    Figures of one run from the ground truth (true pitch theta, x, x_dot) and ~/state.

    balanced: mode BALANCING to the end and |theta| < 10 deg over the last 2 s;
    overshoot [deg]: how far theta went past its final value on the way up (start-up);
    settle [s]: from arm until theta stays within 2 deg of its final value;
    x_span [m], x_dot_mean [m/s]: over the last 5 s; d_hat and theta~ (measured) means over the
    last 5 s [deg] (at standstill the measured pitch is the offset the observer must find).
    """
    m = {'experiment': exp.name, 'notes': list(notes), 'passed': False}
    if t_arm is None or not rec.gt or not rec.state:
        m['notes'].append('no data')
        return m
    gl, sl = rec.gt_labels, rec.state_labels
    t_stop = t_arm + exp.duration   # the robot is disarmed then
    gt = [r for r in rec.gt if t_arm <= r[0] < t_stop]
    st = [r for r in rec.state if t_arm <= r[0] < t_stop]
    t = [r[0] - t_arm for r in gt]
    theta = [math.degrees(v) for v in _column(gt, gl, 'theta')]
    x = _column(gt, gl, 'x')
    x_dot = _column(gt, gl, 'x_dot')
    t_end = t[-1]
    last2 = [th for tt, th in zip(t, theta) if tt >= t_end - 2.0]
    final = sum(last2) / len(last2)
    modes = _column(st, sl, 'mode')
    m['balanced'] = bool(modes and all(v == MODE_BALANCING for v in modes[5:]) and
                         all(abs(th) < 10.0 for th in last2))
    m['theta_start_deg'] = theta[0]
    m['theta_final_deg'] = final
    m['overshoot_deg'] = max(0.0, final - min(theta))
    settle = 0.0
    for tt, th in zip(t, theta):
        if abs(th - final) > 2.0:
            settle = tt
    m['settle_s'] = settle
    m['max_abs_x_dot'] = max(abs(v) for v in x_dot)
    last5 = [i for i, tt in enumerate(t) if tt >= t_end - 5.0]
    m['x_span_last5_m'] = max(x[i] for i in last5) - min(x[i] for i in last5)
    m['x_dot_mean_last5'] = sum(x_dot[i] for i in last5) / len(last5)
    st_t = [r[0] - t_arm for r in st]
    st_last5 = [i for i, tt in enumerate(st_t) if tt >= st_t[-1] - 5.0]
    d_hat = _column(st, sl, 'd_hat')
    theta_meas = _column(st, sl, 'theta')
    m['d_hat_deg'] = math.degrees(sum(d_hat[i] for i in st_last5) / len(st_last5))
    m['theta_meas_deg'] = math.degrees(sum(theta_meas[i] for i in st_last5) / len(st_last5))
    m['imu_offset_deg'] = math.degrees(IMU_OFFSET)
    ok = m['balanced'] and not notes
    if exp.name.startswith('startup'):
        ok = ok and settle < 3.0
    if exp.name == 'standing':
        ok = ok and abs(m['x_dot_mean_last5']) < 0.02 and m['x_span_last5_m'] < 0.1 and \
            abs(m['d_hat_deg'] - m['theta_meas_deg']) < 0.5
    m['passed'] = bool(ok)
    return m


def plot(exp: Experiment, rec: Recorder, t_arm: Optional[float], path: pathlib.Path) -> None:
    """theta, x_dot, wheel torques and d_hat / l over time (0 = arm)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    if not rec.gt or not rec.state:
        return
    t0 = t_arm if t_arm is not None else rec.gt[0][0]
    t_stop = t0 + exp.duration   # disarmed then: what follows is not the experiment
    gt = [r for r in rec.gt if r[0] < t_stop]
    st = [r for r in rec.state if r[0] < t_stop]
    if not gt or not st:
        return
    gl, sl = rec.gt_labels, rec.state_labels
    tg = [r[0] - t0 for r in gt]
    ts = [r[0] - t0 for r in st]
    fig, ax = plt.subplots(4, 1, sharex=True, figsize=(9, 10))
    ax[0].plot(tg, [math.degrees(v) for v in _column(gt, gl, 'theta')], label='theta (true)')
    ax[0].plot(ts, [math.degrees(v) for v in _column(st, sl, 'theta')],
               label='theta~ (IMU)', alpha=0.7)
    ax[0].set_ylabel('pitch [deg]')
    ax[1].plot(tg, _column(gt, gl, 'x_dot'), label='x_dot (true)')
    ax[1].plot(ts, _column(st, sl, 'x_dot'), label='x_dot (odometry)', alpha=0.7)
    ax[1].set_ylabel('speed [m/s]')
    ax[2].plot(ts, _column(st, sl, 'tau_left'), label='tau_left')
    ax[2].plot(ts, _column(st, sl, 'tau_right'), label='tau_right')
    ax[2].set_ylabel('wheel torque [N m]')
    ax[3].plot(ts, [math.degrees(v) for v in _column(st, sl, 'd_hat')],
               label='d_hat [deg]')
    ax[3].plot(tg, [100.0 * v for v in _column(gt, gl, 'l')], label='l [cm]')
    ax[3].set_xlabel('time since arm [s]')
    for a in ax:
        a.grid(True)
        a.legend(loc='upper right')
    ax[0].set_title('%s: %s' % (exp.name, exp.title))
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def write_report(out: pathlib.Path, results: List[dict]) -> None:
    lines = ['# main_job report', '',
             'balance_node against sim_node as separate processes (ROS 2 on localhost, CAN over '
             'udp_multicast); IMU offset d = %.1f deg; figures from sim_node ground truth, '
             'time 0 = arm.' % math.degrees(IMU_OFFSET), '',
             '| experiment | passed | balanced | settle [s] | overshoot [deg] | theta final '
             '[deg] | max abs x_dot [m/s] | x span last 5 s [m] | x_dot mean last 5 s [m/s] | '
             'd_hat [deg] | theta~ [deg] |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for m in results:
        def f(key, fmt='%.3f'):
            return fmt % m[key] if key in m else '-'
        lines.append('| %s | %s | %s | %s | %s | %s | %s | %s | %s | %s | %s |' % (
            m['experiment'], 'yes' if m['passed'] else 'NO', m.get('balanced', '-'),
            f('settle_s', '%.2f'), f('overshoot_deg', '%.1f'), f('theta_final_deg', '%.2f'),
            f('max_abs_x_dot'), f('x_span_last5_m'), f('x_dot_mean_last5'),
            f('d_hat_deg', '%.2f'), f('theta_meas_deg', '%.2f')))
    lines.append('')
    for m in results:
        lines.append('## %s' % m['experiment'])
        lines.append('')
        lines.append('![%s](%s/%s.png)' % (m['experiment'], m['experiment'], m['experiment']))
        for n in m['notes']:
            lines.append('- note: %s' % n)
        lines.append('')
    (out / 'report.md').write_text('\n'.join(lines))


def main(argv=None) -> int:
    """Run the experiments; write plots and report.md into --output."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--output', default='output/main_job_%s' % time.strftime(
        '%Y%m%d_%H%M%S'), help='folder for the report, plots, data and logs')
    parser.add_argument('--only', default='', help='comma-separated experiments (%s)' % ', '.join(
        e.name for e in EXPERIMENTS))
    args = parser.parse_args(argv)
    chosen = [e for e in EXPERIMENTS if not args.only or e.name in args.only.split(',')]
    if not chosen:
        parser.error('no such experiment: %s' % args.only)
    out = pathlib.Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    udp_port = 40000 + os.getpid() % 20000   # keeps concurrent runs apart
    # ROS isolation (main_job.sh sets these too); the child processes inherit them.
    os.environ.setdefault('ROS_DOMAIN_ID', str(100 + os.getpid() % 100))
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rclpy.init()
    rec = Recorder()
    results = []
    try:
        for exp in chosen:
            print('[main_job] %s: %s' % (exp.name, exp.title), flush=True)
            m = run_experiment(exp, rec, out / exp.name, udp_port)
            results.append(m)
            print('[main_job] %s: %s %s' % (exp.name, 'passed' if m['passed'] else 'FAILED',
                                            {k: (round(v, 3) if isinstance(v, float) else v)
                                             for k, v in m.items()}), flush=True)
            write_report(out, results)
    finally:
        rec.close()
        rclpy.try_shutdown()
    print('[main_job] report: %s' % (out / 'report.md'), flush=True)
    return 0 if results and all(m['passed'] for m in results) else 1


if __name__ == '__main__':
    sys.exit(main())
