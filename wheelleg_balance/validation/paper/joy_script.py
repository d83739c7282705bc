"""
joy_script: a scripted joystick; publishes sensor_msgs/Joy on ``joy`` from a timed script.

It stands in for the operator and the joy package's game_controller_node in the main job
(validation/paper/main_job/): teleop_node turns its samples into cmd_vel, cmd_height and arm
requests exactly as it would a real pad's. The stick and button indices come from a
teleop_node parameter file (config/teleop_xbox.yaml: ``axis_linear.x``, ``axis_angular.yaw``,
``enable_button``, ``enable_turbo_button``, ``axis_height``, ``height_buttons`` with
``heights``, ``arm_buttons``, ``disarm_buttons``), so the script speaks of sticks and roles,
not indices (``joy_script`` is ``python -m wheelleg_balance.validation.paper.joy_script``)::

    joy_script --config config/teleop_xbox.yaml --script drive.yaml [--wait-start]

A script (YAML or JSON) is a list of steps; each step sets some of ``linear`` (deflection of
the drive stick, -1..1, up = +1), ``yaw`` (the turn stick, -1..1, left = +1 = turn left),
``turbo`` (hold the turbo button too) and ``enable`` (hold the enable button, the dead man's
switch; true unless set otherwise) and ``height_axis`` (deflection of the height axis, up =
+1) from its time ``t`` [s] on; what a step leaves out keeps its value. A step may also press,
for its own duration only (until the next step), ``height`` (the height button of that height
[m], one of ``heights``), ``arm`` (true: the arm combination, false: the disarm one; held with
the enable button) and ``buttons`` (a list of raw button indices). After ``end`` [s] the pad is
released (sticks centred, no button). Example::

    end: 12.0
    steps:
      - {t: 0.0, arm: true}               # enable + START for 1 s: arms balance_node
      - {t: 1.0}                          # enable held, sticks centred
      - {t: 2.0, linear: 0.64}            # forward: 0.3 m/s at scale_linear.x 0.5
      - {t: 4.0, height: 0.70}            # press Y: cmd_height 0.70 m
      - {t: 4.3}                          # ... and release it
      - {t: 6.0, linear: 0.0, yaw: -1.0, turbo: true}   # spin right at the turbo rate
      - {t: 10.0, yaw: 0.0, turbo: false}

Samples go out at the pad driver's ``autorepeat_rate`` (the ``game_controller_node`` section of
the same file, 20 Hz) or ``--rate``, with 6 axes and 16 buttons (the SDL game controller layout)
or more if an index needs it. Time 0 is the start of the process, or with ``--wait-start`` the
call of the ``~/start`` service (std_srvs/Trigger), which lets a caller line the script up with
other events; until then the released pad is published. After ``end`` the released pad keeps
going out until SIGINT/SIGTERM (``--exit`` ends the process instead, 0.5 s after ``end``).
"""
import argparse
from dataclasses import dataclass, replace
import math
import pathlib
import signal
import sys
import threading
from typing import Dict, List, Optional, Sequence, Tuple

import yaml

#: Joy sizes of the SDL game controller mapping (joy package's game_controller_node).
N_AXES = 6
N_BUTTONS = 16
#: Keys a step may carry.
STEP_KEYS = ('t', 'linear', 'yaw', 'turbo', 'enable', 'height_axis', 'height', 'arm', 'buttons')


@dataclass(frozen=True)
class PadMapping:
    """Where the script's sticks and buttons sit in sensor_msgs/Joy (teleop_node's indices)."""

    axis_linear: int = 1
    axis_yaw: int = 2
    enable_button: int = 9
    turbo_button: int = 10
    rate: float = 20.0   # [Hz]
    axis_height: int = 3
    height_buttons: Tuple[int, ...] = (3, 2, 0)
    heights: Tuple[float, ...] = (0.70, 0.52, 0.37)
    arm_buttons: Tuple[int, ...] = (6,)
    disarm_buttons: Tuple[int, ...] = (4,)

    def height_button(self, height: float) -> int:
        """Return the button of a height [m] (ValueError when no button has it)."""
        for b, h in zip(self.height_buttons, self.heights):
            if abs(h - height) < 1e-6:
                return b
        raise ValueError('no height button for %g m (heights: %s)' % (
            height, ', '.join('%g' % h for h in self.heights) or 'none'))


@dataclass(frozen=True)
class Step:
    """
    Pad state from time t [s] on: stick deflections in [-1, 1] and buttons held.

    height (a height button, by its height [m]), arm (True: the arm combination, False: the
    disarm one) and buttons (raw indices) are pressed for this step only.
    """

    t: float
    linear: float
    yaw: float
    turbo: bool
    enable: bool
    height_axis: float = 0.0
    height: Optional[float] = None
    arm: Optional[bool] = None
    buttons: Tuple[int, ...] = ()


RELEASED = Step(t=0.0, linear=0.0, yaw=0.0, turbo=False, enable=False)


def flatten(d: dict, prefix: str = '') -> dict:
    """Flatten {'a': {'b': 1}} to {'a.b': 1}: parameter files may nest dotted names or not."""
    out = {}
    for k, v in d.items():
        key = prefix + str(k)
        if isinstance(v, dict):
            out.update(flatten(v, key + '.'))
        else:
            out[key] = v
    return out


def load_mapping(path, node: str = 'teleop_node') -> PadMapping:
    """Read the pad layout from a teleop_node parameter file (and the driver's repeat rate)."""
    doc = yaml.safe_load(pathlib.Path(path).read_text()) or {}
    section = doc.get(node) or doc.get('/' + node)
    if not section or 'ros__parameters' not in section:
        raise ValueError('%s has no %s.ros__parameters section' % (path, node))
    p = flatten(section['ros__parameters'])
    d = PadMapping()
    rate = d.rate
    driver = doc.get('game_controller_node', {}).get('ros__parameters', {})
    if driver.get('autorepeat_rate', 0.0) > 0.0:
        rate = float(driver['autorepeat_rate'])

    def indices(key, default):
        return tuple(int(v) for v in p.get(key, default))

    return PadMapping(axis_linear=int(p.get('axis_linear.x', d.axis_linear)),
                      axis_yaw=int(p.get('axis_angular.yaw', d.axis_yaw)),
                      enable_button=int(p.get('enable_button', d.enable_button)),
                      turbo_button=int(p.get('enable_turbo_button', d.turbo_button)),
                      rate=rate, axis_height=int(p.get('axis_height', d.axis_height)),
                      height_buttons=indices('height_buttons', d.height_buttons),
                      heights=tuple(float(v) for v in p.get('heights', d.heights)),
                      arm_buttons=indices('arm_buttons', d.arm_buttons),
                      disarm_buttons=indices('disarm_buttons', d.disarm_buttons))


def _deflection(v, what: str) -> float:
    f = float(v)
    if not -1.0 <= f <= 1.0:
        raise ValueError('%s deflection %r outside [-1, 1]' % (what, v))
    return f


class JoyScript:
    """A parsed script: the pad state at any time (pure Python, no ROS)."""

    def __init__(self, steps: List[Step], end: float):
        self.steps = steps
        self.end = end

    @classmethod
    def from_dict(cls, doc: dict) -> 'JoyScript':
        """Parse {'steps': [...], 'end': s}; values a step leaves out carry over."""
        raw = doc.get('steps') or []
        if not isinstance(raw, list):
            raise ValueError('steps must be a list')
        state = {'linear': 0.0, 'yaw': 0.0, 'turbo': False, 'enable': True, 'height_axis': 0.0}
        steps, last_t = [], -math.inf
        for i, s in enumerate(raw):
            unknown = set(s) - set(STEP_KEYS)
            if unknown:
                raise ValueError('step %d: unknown keys %s' % (i, ', '.join(sorted(unknown))))
            t = float(s.get('t', 0.0))
            if not t >= last_t:
                raise ValueError('step %d: times must not decrease (%g after %g)' % (i, t, last_t))
            last_t = t
            for k in ('linear', 'yaw', 'height_axis'):
                if k in s:
                    state[k] = _deflection(s[k], k)
            for k in ('turbo', 'enable'):
                if k in s:
                    state[k] = bool(s[k])
            press = {}   # this step only
            if s.get('height') is not None:
                press['height'] = float(s['height'])
            if s.get('arm') is not None:
                press['arm'] = bool(s['arm'])
            if s.get('buttons'):
                if not all(isinstance(b, int) and b >= 0 for b in s['buttons']):
                    raise ValueError('step %d: buttons must be indices >= 0' % i)
                press['buttons'] = tuple(s['buttons'])
            steps.append(Step(t=t, **state, **press))
        end = float(doc.get('end', steps[-1].t if steps else 0.0))
        if steps and end < steps[-1].t:
            raise ValueError('end %g before the last step %g' % (end, steps[-1].t))
        return cls(steps, end)

    @classmethod
    def load(cls, path) -> 'JoyScript':
        """Read a script file (YAML, or JSON which is YAML too)."""
        return cls.from_dict(yaml.safe_load(pathlib.Path(path).read_text()) or {})

    def state(self, t: float) -> Step:
        """Pad state at t [s] since the start: before the first step and after end, released."""
        if t < 0.0 or t >= self.end or not self.steps or t < self.steps[0].t:
            return RELEASED
        current = self.steps[0]
        for s in self.steps:
            if s.t > t:
                break
            current = s
        return current


def pressed(step: Step, pad: PadMapping) -> List[int]:
    """Return the button indices a pad state holds (ValueError for a height without button)."""
    held = list(step.buttons)
    if step.enable and pad.enable_button >= 0:
        held.append(pad.enable_button)
    if step.turbo and pad.turbo_button >= 0:
        held.append(pad.turbo_button)
    if step.height is not None:
        held.append(pad.height_button(step.height))
    if step.arm is not None:
        held += list(pad.arm_buttons if step.arm else pad.disarm_buttons)
    return held


def check(script: 'JoyScript', pad: PadMapping) -> None:
    """Raise ValueError when the script presses what the pad mapping does not have."""
    for s in script.steps:
        pressed(s, pad)
        if s.arm is not None and not (pad.arm_buttons if s.arm else pad.disarm_buttons):
            raise ValueError('t=%g: no %s buttons in the teleop file' % (
                s.t, 'arm' if s.arm else 'disarm'))
        if s.height_axis and pad.axis_height < 0:
            raise ValueError('t=%g: no height axis in the teleop file' % s.t)


def joy_arrays(step: Step, pad: PadMapping) -> Tuple[List[float], List[int]]:
    """Joy axes and buttons of a pad state (triggers and unused sticks rest at 0)."""
    held = pressed(step, pad)
    n_axes = max(N_AXES, pad.axis_linear + 1, pad.axis_yaw + 1, pad.axis_height + 1)
    n_buttons = max([N_BUTTONS] + [b + 1 for b in held])
    axes = [0.0] * n_axes
    buttons = [0] * n_buttons
    if pad.axis_linear >= 0:
        axes[pad.axis_linear] = step.linear
    if pad.axis_yaw >= 0:
        axes[pad.axis_yaw] = step.yaw
    if pad.axis_height >= 0 and step.height_axis:
        axes[pad.axis_height] = step.height_axis
    for b in held:
        buttons[b] = 1
    return axes, buttons


def describe(script: JoyScript) -> List[str]:
    """One line per step, for logs and reports."""
    out = []
    for s in script.steps:
        extra = [', turbo' if s.turbo else '', '' if s.enable else ', enable released',
                 ', height axis %+.2f' % s.height_axis if s.height_axis else '',
                 ', press height %.2f m' % s.height if s.height is not None else '',
                 '' if s.arm is None else ', %s combination' % ('arm' if s.arm else 'disarm'),
                 ', buttons %s' % list(s.buttons) if s.buttons else '']
        out.append('t=%5.1f s: linear %+.2f, yaw %+.2f%s' % (s.t, s.linear, s.yaw,
                                                             ''.join(extra)))
    out.append('t=%5.1f s: pad released' % script.end)
    return out


def _node(script: JoyScript, pad: PadMapping, wait_start: bool):
    """
    Return the joy_script node, its ``joy`` publisher, the start time and the script's clock.

    The start time is set on ~/start; the clock [s] counts simulated seconds under use_sim_time
    (main_job in lockstep).
    """
    import rclpy
    from sensor_msgs.msg import Joy
    from std_srvs.srv import Trigger

    from ...nodes.clock import seconds

    node = rclpy.create_node('joy_script')
    pub = node.create_publisher(Joy, 'joy', 10)
    t0: Dict[str, float] = {}
    clock = seconds(node)

    def on_start(request, response):
        if 'start' not in t0:
            t0['start'] = clock()
            node.get_logger().info('script started')
        response.success, response.message = True, 'started'
        return response

    node.create_service(Trigger, '~/start', on_start)
    if not wait_start:
        t0['start'] = clock()
    node.get_logger().info('joy at %.0f Hz, linear axis %d, yaw axis %d, enable button %d, '
                           'turbo button %d; %s' % (
                               pad.rate, pad.axis_linear, pad.axis_yaw, pad.enable_button,
                               pad.turbo_button,
                               'waiting for ~/start' if wait_start else 'started'))
    for line in describe(script):
        node.get_logger().info(line)
    return node, pub, t0, clock


def _publish(node, pub, t0: Dict[str, float], clock, script: JoyScript, pad: PadMapping,
             stop: threading.Event, exit_at_end: bool) -> None:
    """Publish the pad state at ``pad.rate`` until stopped (or 0.5 s after the end)."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import Joy

    executor = SingleThreadedExecutor()
    executor.add_node(node)
    period = 1.0 / pad.rate
    msg = Joy()
    msg.header.frame_id = 'joy'
    next_send = clock()
    last = None
    while not stop.is_set() and rclpy.ok():
        now = clock()
        if now >= next_send:
            t = now - t0['start'] if 'start' in t0 else -1.0
            if exit_at_end and t > script.end + 0.5:
                break
            state = script.state(t)
            msg.axes, msg.buttons = joy_arrays(state, pad)
            msg.header.stamp = node.get_clock().now().to_msg()
            pub.publish(msg)
            if state != last and t >= 0.0:
                node.get_logger().info('t=%.2f s: %s' % (t, state))
                last = state
            next_send += period
            if next_send < now:   # a stall: no burst of stale samples
                next_send = now + period
        executor.spin_once(timeout_sec=max(0.0, min(period, next_send - clock())))


def run(script: JoyScript, pad: PadMapping, wait_start: bool, exit_at_end: bool,
        args: Optional[Sequence[str]] = None) -> int:
    """Publish the script on ``joy`` (ROS); returns the exit code."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node, pub, t0, clock = _node(script, pad, wait_start)
    try:
        _publish(node, pub, t0, clock, script, pad, stop, exit_at_end)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(argv=None) -> int:
    """Parse the command line and publish the script."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0].strip())
    parser.add_argument('--config', required=True,
                        help='teleop_node parameter file with the pad indices '
                             '(config/teleop_xbox.yaml)')
    parser.add_argument('--script', required=True, help='YAML or JSON script (see the module '
                        'docstring)')
    parser.add_argument('--rate', type=float, default=0.0,
                        help='publish rate [Hz] (default: autorepeat_rate of the file, 20)')
    parser.add_argument('--wait-start', action='store_true',
                        help='start the script when ~/start (std_srvs/Trigger) is called')
    parser.add_argument('--exit', action='store_true', help='exit 0.5 s after the end')
    argv = sys.argv[1:] if argv is None else list(argv)
    ros_args = []
    if '--ros-args' in argv:
        i = argv.index('--ros-args')
        argv, ros_args = argv[:i], argv[i:]
    args = parser.parse_args(argv)
    try:
        pad = load_mapping(args.config)
        script = JoyScript.load(args.script)
        check(script, pad)
    except (OSError, ValueError, TypeError, yaml.YAMLError) as exc:
        print('joy_script: %s' % exc, file=sys.stderr)
        return 2
    if args.rate > 0.0:
        pad = replace(pad, rate=args.rate)
    return run(script, pad, args.wait_start, args.exit, [sys.argv[0]] + ros_args)


if __name__ == '__main__':
    sys.exit(main())
