"""
The typed configuration (core/schema.py, core/config.py) and the config files that use it.

Every node section of this package in every file in config/ is checked against the node's
configuration class: no unknown key (rclpy would silently ignore a typo), every value valid,
every parameter documented. Sections of other packages' nodes (the joystick driver's) are left
alone. The schema machinery itself is checked on the real classes.
"""
from dataclasses import dataclass
import math
import pathlib

import pytest

from wheelleg_balance.core.config import BalanceConfig, DEFAULTS
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.core.schema import (check, flatten_yaml, from_flat, nest, param,
                                          section, spec_by_name, specs, to_flat, with_changes)
from wheelleg_balance.nodes.teleop_node import TeleopNodeConfig
from wheelleg_balance.sim.config import SimConfig
import yaml

REPO = pathlib.Path(__file__).resolve().parents[1]
#: This package's nodes and their configuration classes.
NODE_CONFIGS = {'balance_node': BalanceConfig, 'teleop_node': TeleopNodeConfig,
                'sim_node': SimConfig}
#: Nodes of other packages that the config files configure too (left alone).
OTHER_NODES = {'game_controller_node', 'joy_node', 'robot_state_publisher'}
CONFIG_FILES = sorted(p.name for p in (REPO / 'config').glob('*.yaml'))


def _sections():
    for name in CONFIG_FILES:
        doc = yaml.safe_load((REPO / 'config' / name).read_text())
        for node, body in doc.items():
            yield name, node, body


def test_every_config_file_section_is_a_known_node():
    for name, node, _ in _sections():
        assert node in NODE_CONFIGS or node in OTHER_NODES, (name, node)


@pytest.mark.parametrize('name,node,body', [s for s in _sections() if s[1] in NODE_CONFIGS],
                         ids=lambda v: v if isinstance(v, str) else '')
def test_config_file_section_matches_the_schema(name, node, body):
    cls = NODE_CONFIGS[node]
    values = flatten_yaml(body['ros__parameters'])
    known = spec_by_name(cls)
    unknown = sorted(set(values) - set(known))
    assert not unknown, '%s: %s has unknown parameters %s' % (name, node, unknown)
    for key, value in values.items():
        if known[key].kind is float:
            # rclpy refuses an integer for a double parameter: the file must say 1.0, not 1.
            assert isinstance(value, float), '%s: %s = %r must be written as a float' % (
                name, key, value)
    cfg = from_flat(cls, values)   # raises for a value of the wrong type or out of range
    assert check(cfg) == [], (name, check(cfg))


def test_the_robot_file_states_the_defaults():
    """
    Check that config/balance.yaml, the robot's file, sets each value to its default.

    The file says it documents the defaults. It once held max_wheel_velocity 200 rad/s against
    the default's 45, four times what an MIT reply can report: the free-wheel rule never fired.
    """
    body = yaml.safe_load((REPO / 'config' / 'balance.yaml').read_text())['balance_node']
    defaults = to_flat(DEFAULTS)
    differ = {k: (v, defaults[k]) for k, v in flatten_yaml(body['ros__parameters']).items()
              if v != defaults[k]}
    assert not differ, 'config/balance.yaml differs from the defaults (file, default): %s' % (
        differ,)


def test_the_paper_file_over_the_robot_file_is_table_i_as_certified():
    """
    config/paper_table_i.yaml over config/balance.yaml: Table I's gains, the rest the robot's.

    The same set core/margins.py certifies as 'table_i', down to the torques: the tick built
    from the two files and margins.build_core('table_i') give one u for the same state.
    """
    import numpy as np
    from wheelleg_balance.core import margins
    from wheelleg_balance.core.balance_loop import core_config
    from wheelleg_balance.core.lqr import table_i_force_gain
    from wheelleg_balance.core.pipeline import BalanceCore

    def flat(name):
        doc = yaml.safe_load((REPO / 'config' / name).read_text())
        return flatten_yaml(doc['balance_node']['ros__parameters'])
    robot, paper = flat('balance.yaml'), flat('paper_table_i.yaml')
    cfg = from_flat(BalanceConfig, {**robot, **paper})
    assert check(cfg) == []
    assert cfg.ida_pbc == margins.TABLE_I_IDA_PBC
    assert cfg.output_regulation.gain_source == 'table_i'
    assert (cfg.control.yaw_rate_ki, cfg.control.yaw_rate_ff) == (0.0, 0.0)   # Sec. V-A
    # Only gains: nothing of the safety envelope, the wiring or the legs.
    assert set(paper) <= {k for k in paper if k.startswith(('ida_pbc.', 'output_regulation.',
                                                            'yaw_rate_'))}
    from wheelleg_balance.core.pipeline import Measurement, Reference
    for name in ('ida_pbc', 'output_regulation', 'lqr'):
        ours, certified = BalanceCore(cfg.model, core_config(cfg)), margins.build_core('table_i')
        for core in (ours, certified):
            core.select(name)
            core.reset(Measurement(0.05, 0.0, 0.0, 0.0, 0.45))
        for k in range(20):   # a tilted start, the same measurements into both
            m = Measurement(0.05 - 0.001 * k, -0.1, 0.3, 0.3, 0.45)
            u, u_certified = ours.step(m, Reference()).u_cmd, certified.step(m, Reference()).u_cmd
            assert u == u_certified and u != 0.0, (name, k)
    for l in (0.37, 0.55, 0.70):
        assert np.allclose(ours.schedule.gain(l), table_i_force_gain(cfg.model))
    robot_cfg = from_flat(BalanceConfig, robot)
    assert not np.allclose(BalanceCore(robot_cfg.model, core_config(robot_cfg)).schedule.gain(
        0.37), table_i_force_gain(cfg.model))   # the robot's file: the LQR schedule


@pytest.mark.parametrize('cls', list(NODE_CONFIGS.values()))
def test_every_parameter_is_documented_and_has_a_valid_default(cls):
    for s in specs(cls):
        assert s.description and len(s.description) > 10, s.name
        assert s.check(s.default) is None, (s.name, s.check(s.default))
        if s.kind in (int, float) and s.lo is not None:
            assert s.lo <= s.hi, s.name
    assert check(cls()) == []


def test_balance_config_names_and_defaults_of_the_interface():
    flat = to_flat(DEFAULTS)
    # docs/interface.md and Table I.
    assert flat['controller'] == 'auto' and flat['body_mass'] == 11.0
    assert flat['wheel_mass'] == 3.0 and flat['ida_pbc.k'] == 0.015
    assert flat['fall_angle'] == pytest.approx(math.radians(45.0))
    assert flat['can.interface'] == 'socketcan' and flat['can.channel'] == 'can0'
    assert flat['can.right_direction'] == -1 and flat['can.mit.t_max'] == 18.0
    assert flat['ida_pbc.compensate_offset'] is True
    assert spec_by_name(BalanceConfig)['wheel_radius'].read_only
    assert not spec_by_name(BalanceConfig)['controller'].read_only


def test_changes_are_checked_and_leave_the_original_alone():
    new = with_changes(DEFAULTS, {'fall_angle': 0.5, 'can.mit.t_max': 12, 'ida_pbc.k': 0.02})
    assert new.safety.fall_angle == 0.5 and new.can.mit.t_max == 12.0
    assert isinstance(new.can.mit.t_max, float)   # an integer for a double is coerced
    assert new.ida_pbc.k == 0.02 and DEFAULTS.ida_pbc.k == 0.015
    assert new.model is DEFAULTS.model            # untouched sections are shared
    for bad in ({'fall_angle': 3.0}, {'fall_angle': math.nan}, {'controller': 'pid'},
                {'can.left_direction': 0}, {'no_such': 1}, {'fall_angle': 'x'},
                {'output_regulation.q_diag': [1.0, 2.0]}, {'auto_arm': 1}):
        with pytest.raises(ValueError):
            with_changes(DEFAULTS, bad)
    # Cross-field rules are the configuration's own, reported by check().
    assert check(with_changes(DEFAULTS, {'max_wheel_torque': 25.0})) != []
    assert check(with_changes(DEFAULTS, {'can.right_motor_id': 1})) != []
    assert check(with_changes(DEFAULTS, {'left_leg_front_joint': 'a'})) != []
    # Lockstep with the hips in turns on a bus of their own: sim_node could not tell when a
    # tick's hip commands are in (sim/robot_motors.py commanded).
    lockstep = {'legs.driven': True, 'clock_source': 'imu_stamp',
                'can.interface': 'udp_multicast'}
    assert check(with_changes(DEFAULTS, lockstep)) == []
    split = dict(lockstep, **{'legs.can.channel': 'legs'})
    assert any('command_divider' in p for p in check(with_changes(DEFAULTS, split)))
    assert check(with_changes(DEFAULTS, dict(split, **{'legs.command_divider': 1}))) == []


@pytest.mark.parametrize('interface', ['socketcan', 'pcan', 'slcan', 'kvaser', 'socketcand'])
def test_the_lockstep_clock_is_refused_on_a_robot_bus(interface):
    """clock_source imu_stamp only on a test bus: on a robot a dead IMU stops every timeout."""
    for channel in ('can0', 'vcan0', 'sim', '239.74.163.2'):
        for legs in ({}, {'legs.driven': True, 'legs.can.channel': 'can1',
                          'legs.command_divider': 1}):
            changes = dict(legs, **{'clock_source': 'imu_stamp', 'can.interface': interface,
                                    'can.channel': channel})
            found = check(with_changes(DEFAULTS, changes))
            assert len(found) == 1 and 'clock_source' in found[0] \
                and repr(interface) in found[0], found
            # The same bus on the wall clock is the robot's normal set-up.
            assert check(with_changes(DEFAULTS, dict(changes, clock_source='wall'))) == []


@pytest.mark.parametrize('interface', ['virtual', 'udp_multicast', 'socketcan_hub'])
def test_the_lockstep_clock_runs_on_the_test_buses(interface):
    changes = {'clock_source': 'imu_stamp', 'can.interface': interface}
    assert check(with_changes(DEFAULTS, changes)) == []
    assert DEFAULTS.loop.lockstep_wall_timeout == 1.0   # above sim_node's lockstep_timeout
    assert DEFAULTS.loop.lockstep_wall_timeout > SimConfig().lockstep_timeout


def test_flat_and_nested_names_round_trip():
    flat = to_flat(DEFAULTS)
    assert flatten_yaml(nest(flat)) == flat
    assert from_flat(BalanceConfig, flat) == DEFAULTS


def test_a_name_declared_twice_is_refused():
    @dataclass(frozen=True)
    class A:
        x: float = param(1.0, 'the first x [m]')

    @dataclass(frozen=True)
    class B:
        a: A = section(A)
        x: float = param(2.0, 'a second x [m]')
    with pytest.raises(TypeError, match='twice'):
        specs(B)


def test_sim_config_names_defaults_and_rules():
    flat = to_flat(SimConfig())
    # docs/simulation.md: the names sim_node had before the typed configuration.
    assert flat['can.interface'] == 'virtual' and flat['can.mit.t_max'] == 18.0
    assert flat['legs.can.channel'] == '' and flat['legs.motor_ids'] == [3, 4, 5, 6]
    assert flat['slope.angle'] == pytest.approx(math.radians(7.0))
    assert flat['pushes'] == [] and spec_by_name(SimConfig)['pushes'].item is float
    assert all(s.read_only for s in specs(SimConfig))
    # The MIT ranges are balance_node's section: the same names, defaults and codec.
    ranges = ['can.mit.' + k for k in ('p_max', 'v_max', 'kp_max', 'kd_max', 't_max')]
    assert {k: flat[k] for k in ranges} == {k: to_flat(DEFAULTS)[k] for k in ranges}
    # Both sides agree on the firmware's wrapping too.
    assert flat['can.mit.wrap'] == to_flat(DEFAULTS)['can.mit.wrap']
    # The robot as after power-up: hips as MIT motors, folded on the tail, no joint_states.
    cfg = SimConfig()
    assert cfg.initial_pose == 'folded' and cfg.legs.power_up
    assert cfg.publish_joint_states is False and cfg.motor_ids == [1, 2, 3, 4, 5, 6]
    assert 'legs.mode' not in flat and 'height_schedule' not in flat
    assert check(cfg) == []
    for bad in ({'legs.directions': [1, 0, 1, 1]},
                {'legs.motor_ids': [3, 4, 5, 2]},                  # ID of the right wheel
                {'fault.miswired_motor_id': 9},
                {'pushes': [1.0, 0.1, 50.0]},
                {'legs.mit.t_max': 30.0}):
        assert check(with_changes(cfg, bad)) != [], bad
    # On a bus of their own the hips may reuse the wheels' IDs.
    assert check(with_changes(cfg, {'legs.motor_ids': [1, 2, 3, 4],
                                    'legs.can.channel': 'legs'})) == []
    for bad in ({'legs.mode': 'servo'}, {'height_schedule': [0.0, 0.4]},
                {'can.protocol': 'no_such_protocol'}, {'legs.can.protocol': 'dji_c620'},
                {'can.mit.timeout_action': 'stop'},
                {'leg_joints': ['a', 'b']}, {'can.left_direction': 0},
                {'initial_pose': 'lying'}):
        with pytest.raises(ValueError):
            with_changes(SimConfig(), bad)


def _params(name, node):
    doc = yaml.safe_load((REPO / 'config' / name).read_text())
    return flatten_yaml(doc[node]['ros__parameters'])


def test_the_raspberry_pi_overlay_sets_valid_real_time_options_and_nothing_else():
    """config/realtime_pi4.yaml on top of config/balance.yaml: the loop's real-time options."""
    base = _params('balance.yaml', 'balance_node')
    overlay = _params('realtime_pi4.yaml', 'balance_node')
    assert set(overlay) == {'realtime_priority', 'realtime_cpu', 'lock_memory'}
    cfg = from_flat(BalanceConfig, {**base, **overlay})
    assert check(cfg) == []
    assert cfg.loop.realtime_priority == 80 and cfg.loop.realtime_cpu == 3
    assert cfg.loop.lock_memory is True
    assert cfg.can == from_flat(BalanceConfig, base).can   # the robot's wiring untouched


def test_the_sim_files_wire_balance_node_to_the_simulated_robot():
    """config/balance_sim.yaml against config/sim.yaml: one bus, the same motors, hips driven."""
    sim = from_flat(SimConfig, _params('sim.yaml', 'sim_node'))
    bal = from_flat(BalanceConfig, _params('balance_sim.yaml', 'balance_node'))
    assert check(sim) == [] and check(bal) == []
    for key in ('interface', 'channel', 'udp_port', 'left_motor_id', 'right_motor_id',
                'left_direction', 'right_direction'):
        assert getattr(bal.can, key) == getattr(sim.can, key), key
    # The codec's ranges must match (the frames' scaling); the health figures are the host's.
    for key in ('p_max', 'v_max', 'kp_max', 'kd_max', 't_max'):
        assert getattr(bal.can.mit, key) == getattr(sim.can.mit, key), key
        assert getattr(bal.legs.mit, key) == getattr(sim.legs.mit, key), key
    assert bal.wheel_state.position_wraps == sim.can.firmware.wrap
    assert bal.legs.driven and bal.wheel_state.wheel_state_source == 'can'
    assert (bal.legs.motor_ids, bal.legs.directions) == (sim.legs.motor_ids,
                                                         sim.legs.directions)
    assert bal.legs.channel == sim.legs.can_channel
    # Readings known modulo a rotor turn after power-up: the hips must be homed on their stops.
    assert sim.legs.power_up and bal.legs.homing == 'hard_stops'
    assert bal.legs.stop_angles == [FiveBarLeg().q_min] * 4     # robot.xml's hip range
    assert sim.initial_pose == 'folded' and not sim.publish_joint_states
    assert bal.safety.auto_arm and not any(bal.joints.leg_names)
    # The robot's file drives nothing of the sort: it arms only when asked.
    robot = from_flat(BalanceConfig, _params('balance.yaml', 'balance_node'))
    assert not robot.safety.auto_arm


def test_an_unset_parameter_needs_its_type():
    @dataclass(frozen=True)
    class A:
        flag: bool = param(None, 'on or off (unset: decided by the node)', kind=bool)
    (s,) = specs(A)
    assert s.kind is bool and s.default is None and s.check(None) is None
    assert s.check(1) is not None and with_changes(A(), {'flag': True}).flag is True

    @dataclass(frozen=True)
    class B:
        flag: bool = param(None, 'on or off, no type given')
    with pytest.raises(TypeError, match='kind'):
        specs(B)
