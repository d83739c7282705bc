"""Every fault scenario by name, in report order, and the runner of the tests and the report."""
from typing import Callable, Dict, List

import rclpy
from rclpy.context import Context

from . import lockstep as ls, scenarios as sc
from .matrices import MATRICES, matrix_scenario, scenario_joy_fields
from .outcome import Outcome
from ..contention import CpuContention, CpuHistory

SCENARIOS: Dict[str, Callable[[Context], Outcome]] = {
    'imu_silent': sc.scenario_imu_silent,
    'imu_frozen': sc.scenario_imu_frozen,
    'imu_nan': sc.scenario_imu_nan,
    'imu_rate_inf': sc.scenario_imu_rate_inf,
    'quaternion_not_unit': sc.scenario_quaternion_not_unit,
    'wheel_velocity_nan': sc.scenario_wheel_velocity_nan,
    'wheel_joints_missing': sc.scenario_wheels_missing,
    'leg_out_of_reach': sc.scenario_leg_out_of_reach,
    'cmd_vel_invalid': sc.scenario_cmd_vel_invalid,
    'cmd_vel_stale': sc.scenario_cmd_vel_stale,
    'cmd_vel_future': sc.scenario_cmd_vel_future,
    'second_imu_publisher': sc.scenario_second_imu_publisher,
    'second_cmd_vel_publisher': sc.scenario_second_cmd_vel_publisher,
    'second_commander': sc.scenario_second_commander,
    'joy_fields': scenario_joy_fields,
    'motor_silent': sc.scenario_motor_silent,
    'reply_unknown_id': sc.scenario_unknown_reply_id,
    'stranger_replies': sc.scenario_stranger_replies,
    'motor_error': sc.scenario_motor_error,
    'motor_rebooted': sc.scenario_motor_rebooted,
    'motor_over_temperature': sc.scenario_motor_over_temperature,
    'imu_stamp_future': sc.scenario_imu_stamp_future,
    'imu_stamp_backwards': sc.scenario_imu_stamp_backwards,
    'can_tx_queue_full': sc.scenario_tx_queue_full,
    'can_bus_off': sc.scenario_bus_off,
    'error_frame_storm': sc.scenario_error_frame_storm,
    'fall_forward': sc.scenario_fall_forward,
    'fall_backward': sc.scenario_fall_backward,
    'push_fall_sim_node': sc.scenario_sim_node_push,
    'bad_parameters': sc.scenario_bad_parameters,
    'loosen_while_balancing': sc.scenario_loosen_while_balancing,
    'controller_switch_1mps': ls.scenario_controller_switch,
    'recovery_rearm': ls.scenario_recovery_needs_rearm,
    'lifted': ls.scenario_lifted,
    'lifted_tilted_15': lambda context: ls.scenario_lifted(context, 15.0),
    # The default robot: legs not driven (issue 29).
    'lifted_fixed_legs': lambda context: ls.scenario_lifted(context, 0.0, driven=False),
    'lifted_fixed_legs_tilted_3': lambda context: ls.scenario_lifted(context, 3.0, driven=False),
    'lifted_fixed_legs_tilted_15':
        lambda context: ls.scenario_lifted(context, 15.0, driven=False),
    'imu_flipped_fixed_legs': ls.scenario_imu_flipped,
    'imu_flipped': lambda context: ls.scenario_imu_flipped(context, driven=True),
    'imu_flipped_plant': ls.scenario_imu_flipped_plant,
    'sigint_shutdown': sc.scenario_sigint,
    'sigterm_shutdown': sc.scenario_sigterm,
    'sighup_shutdown': sc.scenario_sighup,
    'sigquit_shutdown': sc.scenario_sigquit,
    'control_process_stalled': sc.scenario_control_stalled,
    'control_process_killed': sc.scenario_control_killed,
    'balance_node_killed': sc.scenario_node_killed,
}
# The timeout scenarios again at the robot's own timeouts (50 ms), not the rig's doubled ones.
SCENARIOS.update({'%s_%dms' % (name, round(1e3 * sc.ROBOT_TIMEOUTS['imu_timeout'])):
                  (lambda f: lambda context: f(context, sc.ROBOT_TIMEOUTS))(SCENARIOS[name])
                  for name in ('imu_silent', 'imu_frozen', 'wheel_joints_missing',
                               'motor_silent')})
SCENARIOS.update({name: matrix_scenario(name, kind, cases, params)
                  for name, (kind, cases, params) in MATRICES.items()})
# The motor faults and the second commander on the other wheel protocols (issue 31): the
# fake motors are the configured protocol's emulator.
SCENARIOS.update({'%s_%s' % (name, wheels): (lambda f, w: lambda context: f(context, wheels=w))(
    SCENARIOS[name], wheels) for wheels, names in sc.PROTOCOL_FAULTS.items() for name in names})


#: The window before the injection over which the machine's contention is judged [s].
BEFORE_INJECTION = 2.0


def run_measured(name: str, context: Context) -> Outcome:
    """
    Run scenario ``name``; its figures also get the machine's CPU contention.

    ``cpu_pressure_pct`` and ``cpu_steal_pct`` over the whole run, and where the scenario marks
    its injection, ``cpu_pressure_before_pct`` and ``cpu_steal_before_pct`` over the
    BEFORE_INJECTION seconds before it (validation/contention.py): what a failure can be
    attributed to.
    """
    contention = CpuContention()
    with CpuHistory() as history:
        outcome = SCENARIOS[name](context)
        if outcome.injected_at is not None:
            before = history.window(outcome.injected_at - BEFORE_INJECTION,
                                    outcome.injected_at)
            outcome.figures['cpu_pressure_before_pct'] = before['cpu_pressure_pct']
            outcome.figures['cpu_steal_before_pct'] = before['cpu_steal_pct']
    outcome.figures.update(contention.figures())
    return outcome


def run_scenarios(names=None, context=None, progress=None) -> List[Outcome]:
    """
    Run the named scenarios (all when None) and return their outcomes.

    A scenario that raises is reported as not handled, with the exception as its failed check.
    ``context``: an initialized rclpy Context (one is made and shut down when None).
    """
    own = context is None
    if own:
        context = Context()
        rclpy.init(context=context)
    outcomes = []
    try:
        for name in names or list(SCENARIOS):
            try:
                outcome = run_measured(name, context)
            except Exception as exc:  # noqa: B902 -- a crashed scenario is a result too
                outcome = Outcome(name, name, '(scenario crashed)')
                outcome.check('scenario ran: %s: %s' % (type(exc).__name__, exc), False)
            outcomes.append(outcome)
            if progress is not None:
                progress(outcome)
    finally:
        if own:
            rclpy.try_shutdown(context=context)
    return outcomes
