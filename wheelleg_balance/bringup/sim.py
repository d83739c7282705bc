"""
``bringup --sim``: the same procedure against sim_node, whose hand does the builder's part.

sim_node runs with the hip motors on CAN, on the bring-up stand
(``initial_pose: stand``: body at the tail pitch, wheels free, powered up with the legs
folded), on a udp_multicast bus of its own. ``sim_params`` writes its parameters (the caller's
``NAME=VALUE`` overrides on top, e.g. ``fault.miswired_motor_id=1``); ``balance_config`` is
what the builder believes about that robot: sim_node's IDs, directions and offsets as
configured (a miswired motor is the simulator's secret, which the check must find).
``SimOperator`` answers each step by publishing on sim_node's ``~/hand`` (sim/hand.py): the
wheel turned forward by 1 rad, the leg folded onto its stop, then stretched 0.3 rad off it.
"""
import time
from typing import Callable, Dict, List, Mapping, Sequence

from .motor_checks import MotorSlot
from .session import Operator
from ..core.config import BalanceConfig
from ..core.protocols import protocol_class
from ..core.schema import check, from_flat, spec_by_name, to_flat, with_changes
from ..sim.config import motor_protocol, SimConfig

#: The hand's moves [rad] and torque limits [N m] per step (joint conventions, sim/hand.py).
HAND = {'wheel_forward': (1.0, 0.5), 'leg_fold': (-3.0, 4.0), 'leg_stretch': (0.3, 4.0)}
#: How long the hand takes for a step [s of sim time: ``wait`` follows sim_node's /clock].
HAND_TIME = 1.5


def sim_params(can_group: str, udp_port: int, overrides: Mapping[str, object] = ()
               ) -> Dict[str, object]:
    """Return sim_node's parameters for bring-up (checked against SimConfig)."""
    flat = {'can.interface': 'udp_multicast', 'can.channel': can_group,
            'can.udp_port': udp_port, 'initial_pose': 'stand',
            'ground_truth_rate': 0.0}
    flat.update(dict(overrides))
    problems = check(from_flat(SimConfig, flat))   # from_flat: ValueError for a bad value
    if problems:
        raise ValueError('; '.join(problems))
    return flat


def balance_config(sim: SimConfig) -> BalanceConfig:
    """
    Return the balance_node configuration a builder would write for sim_node's robot.

    Each motor set's protocol with its figures: the section the protocol names (``can.lk``,
    ``legs.damiao``, ...), as sim_node has it, balance_node's parameters of it only (sim_node
    adds firmware options such as ``can.mit.wrap``); max_wheel_torque at most what the wheel
    motors give.
    """
    c, legs = sim.can, sim.legs
    known = spec_by_name(BalanceConfig)
    prefixes = tuple('%s.%s.' % (owner, protocol_class(name).config_section)
                     for owner, name in (('can', c.protocol), ('legs', legs.protocol))
                     if protocol_class(name).config_section)
    figures = {k: v for k, v in to_flat(sim).items() if k.startswith(prefixes) and k in known}
    wheel_limit = min(BalanceConfig().safety.max_wheel_torque, motor_protocol(c).torque_limit)
    return with_changes(BalanceConfig(), dict(figures, **{
        'max_wheel_torque': wheel_limit,
        'can.interface': c.interface, 'can.channel': c.channel, 'can.udp_port': c.udp_port,
        'can.protocol': c.protocol,
        'can.left_motor_id': c.left_motor_id, 'can.right_motor_id': c.right_motor_id,
        'can.left_direction': c.left_direction, 'can.right_direction': c.right_direction,
        'legs.driven': True, 'legs.motor_ids': list(legs.motor_ids),
        'legs.directions': list(legs.directions), 'legs.offsets': list(legs.offsets),
        'legs.can.channel': legs.can_channel, 'legs.can.protocol': legs.protocol,
        'legs.homing': 'set_zero',
        'imu_timeout': 0.5, 'joint_state_timeout': 0.5, 'motor_timeout': 0.5,
        'watchdog_timeout': 0.5,
    }))


def joint_names(sim: SimConfig) -> Dict[str, str]:
    """Return {slot key: sim_node's joint name} (the names ~/hand takes)."""
    hips = ('left_front', 'left_rear', 'right_front', 'right_rear')
    out = {'left_wheel': sim.left_wheel_joint, 'right_wheel': sim.right_wheel_joint}
    out.update(zip(hips, sim.leg_joints))
    return out


class SimOperator(Operator):
    """
    The simulator's hand as the builder (see the module docstring).

    hand(names, positions, efforts): publishes a sensor_msgs/JointState on sim_node's ~/hand
    (empty names: let go); say: where the moves are told; wait(seconds): waits that long on
    sim_node's clock.
    """

    def __init__(self, sim: SimConfig, hand: Callable[[List[str], List[float], List[float]],
                                                      None],
                 say: Callable[[str], None] = print, hand_time: float = HAND_TIME,
                 wait: Callable[[float], None] = time.sleep):
        self._names = joint_names(sim)
        self._hand = hand
        self._say = say
        self.hand_time = hand_time
        self._wait = wait

    def ask(self, step: str, slots: Sequence[MotorSlot], text: str) -> None:
        """Tell the step, move the joints with the hand, wait until it is done."""
        move, limit = HAND[step]
        names = [self._names[s.key] for s in slots]
        self._say('>>> ' + text)
        self._say('    [sim] the hand moves %s by %+.2f rad (at most %.1f N m)'
                  % (', '.join(names), move, limit))
        self._hand(names, [move] * len(names), [limit] * len(names))
        self._wait(self.hand_time)

    def done(self) -> None:
        """Let go."""
        self._hand([], [], [])
