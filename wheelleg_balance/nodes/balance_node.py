"""
balance_node: the ROS face of the robot's 2 ms balance loop (interface: docs/interface.md).

The tick itself is core/balance_loop.py; it runs in a control process of its own
(nodes/control_process.py) that owns the CAN bus, so nothing this process does (the rclpy
executor, parameter and service calls, DDS discovery of other processes) can delay it
(docs/benchmarks.md). ``imu`` and ``joint_states`` reach it from a sensor intake process that
has nothing but the two subscriptions (nodes/sensor_intake.py); a watchdog process stops the
motors if the control process stalls or dies (nodes/watchdog.py). This node is the shell around
them:

- parameters from the typed configuration (core/config.py), validated together, forwarded to
  the loop, which applies them at its next tick; ``cmd_vel`` and ``cmd_height`` from the
  executor;
- ``~/arm`` (std_srvs/SetBool) forwarded, answered with the loop's reply; ``~/stop``
  (std_srvs/Trigger): the software emergency stop, zero torque and the motors to rest at once;
  ``~/excite/stand``, ``~/excite/tail``, ``~/excite/balance`` (std_srvs/Trigger): an
  identification phase (core/excitation.py), answered like ``~/arm``;
- ``~/state``, ``odom``, ``joint_states`` (the six motors and the passive knees) and TF
  (base_footprint -> base_link, odom -> base_footprint with ``enable_odom_tf``) published from
  what the loop sends back, each while it has a subscription (the loop sends no frame nobody
  reads: nodes/state_publisher.py), ``/diagnostics`` from its status (nodes/diagnostics.py).

Modes (core/safety.py): DISARMED sends no frames (the motors were left in rest mode by the exit
frames), BALANCING sends the controller's torques, FAULT sends zero torque every tick until an
explicit re-arm or disarm, EXCITING an identification phase's torques. See docs/balance_node.md.
"""
import gc
import itertools
import signal
import sys
import threading
import time
from typing import Callable, Dict, Optional, Tuple

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import TwistStamped
import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from rclpy.signals import uninstall_signal_handlers
from std_msgs.msg import Float64
from std_srvs.srv import SetBool, Trigger

from . import control_link as L, input_guard, lean
from .diagnostics import diagnostic_array
from .loop_processes import LoopProcesses, START_TIMEOUT  # noqa: F401 (START_TIMEOUT)
from .params import load, ParameterGuard
from .state_publisher import StatePublisher
from ..core.config import BalanceConfig
from ..core.excitation import PHASES
from ..core.safety import Mode
from ..core.tick_io import CmdHeight, CmdVel, MODE
from ..processes import StartError

#: How long ~/arm waits for the loop's answer [s].
ARM_TIMEOUT = 1.0
#: A status older than this [s] means the control loop is not alive (it sends five a second).
ALIVE_LIMIT = 0.5


class BalanceNode(Node):
    """The balance controller's ROS shell (see the module docstring)."""

    def __init__(self, bus=None, **kwargs):
        """
        Build the node and start its control loop.

        bus: an already open python-can bus: the control loop then runs in a thread of this
        process on it (tests with an in-process ``virtual`` bus); None: in its own process on
        the bus of ``can.interface`` / ``can.channel``. kwargs go to rclpy's Node.
        """
        super().__init__('balance_node', **kwargs)
        self.config = load(self, BalanceConfig)   # ValueError with every problem
        cfg = self.config
        self._guard = ParameterGuard(cfg, self._forward_parameters, self._commanding)
        self._loop_mode = int(Mode.DISARMED)   # the loop's, from its newest state or status
        self._hardware_id = '%s:%s' % (cfg.can.interface, cfg.can.channel)
        self._status: Optional[dict] = None
        self._status_key = None
        self._diag_lock = threading.Lock()
        self._diag_on_change = False   # set once the inputs (and the diagnostics timer) exist
        self._arm_ids = itertools.count(1)
        self._arm_waiting: Dict[int, list] = {}
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._ready = threading.Event()
        self._control_error = ''
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10,
                                               event_callbacks=lean.publisher_events())
        self._publisher = StatePublisher(
            self, cfg, lambda flags: self.link.send_object(L.WANTED, flags))
        # The GIL is handed over every 5 ms by default: far too late for a control loop in a
        # thread of this process (tests) when the executor is busy in Python.
        sys.setswitchinterval(min(sys.getswitchinterval(), 0.0002))
        self._start_children(bus)
        self._publisher.report_wanted()   # then on every change (the publishers' events)
        self._make_inputs(cfg)
        self.get_logger().info(
            'balance_node: controller %s, CAN %s (%s, motors %d/%d), %.1f ms loop in %s, %s' % (
                cfg.control.controller, self._hardware_id, cfg.can.protocol,
                cfg.can.left_motor_id, cfg.can.right_motor_id, 1e3 * cfg.loop.control_period,
                'a thread (in-process bus)' if bus is not None else 'its own process',
                'auto_arm' if cfg.safety.auto_arm else 'call ~/arm to balance'))

    # ------------------------------------------------------------------------------ set-up

    def _start_children(self, bus) -> None:
        """Start the control loop, the sensor intake, the watchdog; wait until they run."""
        self._reader = threading.Thread(target=self._read_link, name='balance_link',
                                        daemon=True)
        self._procs = LoopProcesses()
        self.link = self._procs.link
        _on_shutdown_signal(self.stop_loop)
        try:
            self._procs.start(self, self.config, bus)
            self._reader.start()
            self._procs.wait_started(self._ready, lambda: self._status,
                                     lambda: self._control_error)
        except BaseException:
            # Whatever stopped the start (an error, a signal), the motors end at zero torque.
            self.shutdown()
            raise

    def _make_inputs(self, cfg: BalanceConfig) -> None:
        """Create the command subscriptions, the services, the timer, the parameter guard."""
        no_events = lean.subscription_events()
        self.create_subscription(TwistStamped, 'cmd_vel', self._on_cmd_vel,
                                 qos_profile_sensor_data, event_callbacks=no_events)
        self.create_subscription(Float64, 'cmd_height', self._on_cmd_height, 10,
                                 event_callbacks=no_events)
        self.create_service(SetBool, '~/arm', self._on_arm)
        for phase in PHASES:   # one Trigger per phase: std_srvs has no request with a name
            self.create_service(Trigger, '~/excite/' + phase,
                                lambda request, response, phase=phase:
                                self._on_excite(phase, response))
        self.create_service(Trigger, '~/stop', self._on_stop)
        # At the diagnostics rate; a new mode or fault publishes at once from the link's
        # reader (_on_status). An executor wake-up costs rclpy about 0.2 ms: polling for a
        # change 20 times a second cost the node more than its publishing (docs/benchmarks.md).
        self.create_timer(1.0 / cfg.publish.diagnostics_rate, self._on_diagnostics_timer)
        self._diag_on_change = True
        self.input_guard = input_guard.InputGuard(
            self, cfg, lambda found: self.link.send_object(L.CONFLICTS, found))
        self.create_timer(input_guard.CHECK_PERIOD, self.input_guard.check)
        self.add_on_set_parameters_callback(self._guard)

    # --------------------------------------------------------------- from the control loop

    def _read_link(self) -> None:
        link = self.link
        while not link.closed:
            if not link.wait_readable(0.1):
                continue
            for tag, payload in link.receive():
                try:
                    self._on_message(tag, payload)
                except Exception as exc:  # noqa: B902 -- a lost message is not a fault
                    if not self._closing.is_set():
                        self.get_logger().warning('control link: %r' % (exc,),
                                                  throttle_duration_sec=1.0)
        if not self._closing.is_set():
            self._control_error = self._control_error or 'control loop ended'
            if self._ready.is_set():   # else a failed start: its one line ends the node
                self.get_logger().error('control loop process ended: the motors got its stop '
                                        'frames if it could send them')
        self._ready.set()

    def _commanding(self) -> bool:
        """Return True while the motors are commanded or an arm request is under way."""
        return self._loop_mode != int(Mode.DISARMED) and self._loop_mode != int(Mode.FAULT) \
            or bool(self._arm_waiting)

    def _on_message(self, tag: bytes, payload) -> None:
        if tag == L.STATE:
            values, joints = payload
            self._loop_mode = int(values[MODE])
            if not self.context.ok() or self._closing.is_set():
                return
            self._publisher.publish(values, joints)
        elif tag == L.STATUS:
            self._status = payload
            self._loop_mode = int(payload['mode_index'])
            if self._diag_on_change and self.context.ok() and not self._closing.is_set():
                self._publish_diagnostics(changed_only=True)
        elif tag == L.ARM_REPLY:
            request_id, ok, message = payload
            with self._lock:
                waiting = self._arm_waiting.get(request_id)
            if waiting is not None:
                waiting[1] = (ok, message)
                waiting[0].set()
        elif tag == L.EVENT:
            self._log_event(*payload)
        elif tag == L.READY:
            self.get_logger().info(payload)
            self._ready.set()

    def _log_event(self, level: str, text: str) -> None:
        # One call site per severity: rclpy refuses a call site whose severity changes.
        log = self.get_logger()
        if level == 'info':
            log.info(text)
        elif level == 'warn':
            log.warning(text)
        else:
            log.error(text)
            if not self._ready.is_set():
                self._control_error = text

    # ------------------------------------------------------------------- to the control loop

    def _on_cmd_vel(self, msg: TwistStamped) -> None:
        self.link.send_cmd_vel(CmdVel(time.monotonic(), msg.twist.linear.x,
                                      msg.twist.angular.z))

    def _on_cmd_height(self, msg: Float64) -> None:
        self.link.send_cmd_height(CmdHeight(time.monotonic(), msg.data))

    def _on_stop(self, request, response):
        response.success = self.link.send_object(L.ESTOP, None)
        response.message = 'stopped: zero torque, motors to rest' if response.success else \
            'control loop not reachable'
        self.get_logger().warning('~/stop: %s' % response.message)
        return response

    def _on_arm(self, request, response):
        response.success, response.message = self._ask(bool(request.data))
        self.get_logger().info('~/arm %s: %s (%s)' % (
            request.data, 'ok' if response.success else 'refused', response.message))
        return response

    def _on_excite(self, phase: str, response):
        response.success, response.message = self._ask(phase)
        self.get_logger().info('~/excite/%s: %s (%s)' % (
            phase, 'ok' if response.success else 'refused', response.message))
        return response

    def _ask(self, request) -> Tuple[bool, str]:
        """Send an arm request (True, False or a phase's name); return the loop's answer."""
        request_id = next(self._arm_ids)
        waiting = [threading.Event(), None]
        with self._lock:
            self._arm_waiting[request_id] = waiting
        self.link.send_object(L.ARM, (request_id, request))
        answer = waiting[1] if waiting[0].wait(ARM_TIMEOUT) else \
            (False, 'control loop did not answer')
        with self._lock:
            self._arm_waiting.pop(request_id, None)
        return answer

    def _forward_parameters(self, changes, new_config) -> None:
        self.config = new_config
        self.link.send_object(L.PARAMS, changes)

    # ---------------------------------------------------------------------------- diagnostics

    def _on_diagnostics_timer(self) -> None:
        if self._closing.is_set():   # the executor may still spin while shutdown() runs
            return
        self._publish_diagnostics(changed_only=False)

    def _publish_diagnostics(self, changed_only: bool) -> None:
        """Publish /diagnostics (changed_only: only if the mode or the faults changed)."""
        with self._diag_lock:   # the timer's thread and the link's reader
            st = self._status
            key = None if st is None else (st['mode'], tuple(st['faults']))
            if changed_only and key == self._status_key:
                return
            self._status_key = key
            msg = self.diagnostics(time.monotonic())
        self._diag_pub.publish(msg)

    @property
    def control_task_id(self) -> Optional[int]:
        """Return the Linux task the control loop runs in: its process's pid or thread id."""
        return self._procs.control_task_id

    @property
    def control_ticks(self) -> Optional[int]:
        """Return the ticks the control loop has run in this process (None: in its own)."""
        runner = self._procs.runner
        return None if runner is None else runner.ticks

    @property
    def status(self) -> Optional[dict]:
        """Return the newest status the control loop sent (BalanceLoop.status + timing)."""
        return self._status

    def diagnostics(self, now: float):
        """Build the DiagnosticArray of the newest status of the control loop."""
        return diagnostic_array(self._status, self._hardware_id, now, ALIVE_LIMIT,
                                self.get_clock().now().to_msg(),
                                None if self._procs.watchdog is None
                                else self._procs.watchdog.state())

    # ------------------------------------------------------------------------------ shutdown

    def shutdown(self) -> None:
        """Stop the loop (zero torque, exit motor mode, bus closed), then the link (idempotent)."""
        if self._closing.is_set():
            return
        self._closing.set()
        procs = self._procs
        self.stop_loop()   # first: the intake takes a while to end
        procs.end_children()
        if self._reader.is_alive():
            self._reader.join(timeout=1.0)
        procs.close()

    def stop_loop(self) -> None:
        """Tell the control loop to stop now: zero torque, exit frames (from a signal handler)."""
        self.link.send_object(L.STOP, None)

    def destroy_node(self):
        """Shut down (stop the loop, zero torque, close the bus), then destroy the node."""
        self.shutdown()
        return super().destroy_node()


#: The running node's first step of a shutdown signal: tell the control loop to stop (zero
#: torque, exit frames) at once, before rclpy's executor has noticed the shutdown (that took up
#: to 0.4 s; a signal during start-up waited for the rest of the constructor).
_stop_loop_now: Optional[Callable[[], None]] = None


def _on_shutdown_signal(stop: Callable[[], None]) -> None:
    global _stop_loop_now
    _stop_loop_now = stop


def _stop_on_signal(signum, frame) -> None:
    """SIGINT / SIGTERM: stop the loop now; rclpy's own handler shuts the context down."""
    if _stop_loop_now is not None:
        _stop_loop_now()


def _shutdown_on_signal(signum, frame) -> None:
    """SIGHUP / SIGQUIT (an ssh session that drops): shut down as on SIGINT."""
    _stop_on_signal(signum, frame)
    rclpy.try_shutdown()


def main(args=None) -> int:
    """Run balance_node until a signal; exit with zero torque and the motors disabled."""
    # SIGINT and SIGTERM: rclpy's handlers shut rclpy down and chain to these, which stop the
    # loop at once; no KeyboardInterrupt may land in the constructor or the stop path and skip
    # the exit frames.
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, _stop_on_signal)
    rclpy.init(args=args)
    for signum in (signal.SIGHUP, signal.SIGQUIT):
        signal.signal(signum, _shutdown_on_signal)
    # Made before the node: the loop balances from the start, so a signal can come before
    # spinning begins, and an executor cannot be created on a context already shut down.
    executor = SingleThreadedExecutor()
    node = None
    rc = 0
    try:
        node = BalanceNode()
        gc.collect()
        gc.freeze()
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except StartError as exc:   # a child's line (what, why, the fix), or the node's own
        if rclpy.ok():
            print('balance_node: %s' % exc, file=sys.stderr)
            rc = 1
    except Exception as exc:  # noqa: B902 -- one clear line, no traceback
        if rclpy.ok():  # else a signal shut rclpy down while we started or spun: not an error
            print('balance_node: %s: %s' % (type(exc).__name__, exc), file=sys.stderr)
            rc = 1
    finally:
        if node is not None:
            node.destroy_node()  # stops the loop: zero torque, exit frames, bus closed
        executor.shutdown()
        rclpy.try_shutdown()
        # try_shutdown leaves rclpy's signal handler thread running; join it before exit.
        uninstall_signal_handlers()
    return rc


if __name__ == '__main__':
    sys.exit(main())
