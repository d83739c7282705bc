"""
A simulated robot that is not the default: sim_node's ``robot.*`` (sim/variant.py).

The defaults compile to robot.xml's model; each changed quantity changes the physics as it
should: a free wheel's deceleration with bearing damping, its inertia, the delay between a torque
command and the wheel's response, the static lean against the body's centre of mass, the wheel
radius in the rolling and in the contact; a wrong value is refused with a one-line reason.
"""
import math

import mujoco
import numpy as np
import pytest

from wheelleg_balance.core.schema import check, from_flat
from wheelleg_balance.sim.config import RobotBodyConfig, SimConfig
from wheelleg_balance.sim.robot_sim import CONTACT_DEPTH, MODEL_PATH, RobotSim


def _body(**changes):
    return from_flat(RobotBodyConfig, changes)


def _on_stand(body):
    sim = RobotSim(body=body)
    sim.hold(pitch=0.0, z=1.0)   # the wheels hang free
    return sim


def test_the_defaults_are_robot_xml():
    plain = mujoco.MjModel.from_xml_path(str(MODEL_PATH))
    sim = RobotSim(body=RobotBodyConfig())
    m = sim.model
    for name in ('body_mass', 'body_inertia', 'body_ipos', 'body_iquat', 'geom_size',
                 'dof_damping', 'dof_armature'):
        assert np.array_equal(getattr(m, name), getattr(plain, name)), name
    # The same bits after a second of falling onto the tail with torques.
    ref = RobotSim()
    for s in (sim, ref):
        s.reset('pitch', pitch=0.05)
        s.step(1.0, 0.5, 1.0)
    assert np.array_equal(sim.data.qpos, ref.data.qpos)


def test_wheel_damping_decelerates_a_free_wheel_at_b_over_i():
    inertia, damping = 0.009, 0.05
    sim = _on_stand(_body(wheel_inertia=inertia, wheel_damping=damping))
    sim.step(3.0, 3.0, 0.2)
    w0 = sim.wheel_velocities()[0]
    sim.step(0.0, 0.0, 0.5)
    w1 = sim.wheel_velocities()[0]
    # I w_dot = -b w: w decays as exp(-b t / I).
    rate = math.log(w0 / w1) / 0.5
    assert rate == pytest.approx(damping / inertia, rel=0.02)
    # Without damping the free wheel keeps its speed.
    plain = _on_stand(_body(wheel_inertia=inertia))
    plain.step(3.0, 3.0, 0.2)
    v0 = plain.wheel_velocities()[0]
    plain.step(0.0, 0.0, 0.5)
    assert plain.wheel_velocities()[0] == pytest.approx(v0, rel=1e-3)
    # The torque step's acceleration was tau / I.
    assert v0 == pytest.approx(3.0 * 0.2 / inertia, rel=0.01)


@pytest.mark.parametrize('delay', [0.0, 0.004, 0.0063])
def test_the_motor_delay_is_the_time_from_command_to_response(delay):
    driven, idle = (_on_stand(_body(motor_delay=delay)) for _ in range(2))
    for sim in (driven, idle):
        sim.step(0.0, 0.0, 0.5)   # the legs settle on the stand
    start, seen = driven.time, None
    for _ in range(100):
        driven.step(2.0, 2.0, driven.timestep)
        idle.step(0.0, 0.0, idle.timestep)
        if seen is None and driven.wheel_velocities()[0] - idle.wheel_velocities()[0] > 1e-6:
            seen = driven.time - start
    # The wheel answers within the physics step after the delay.
    assert delay < seen <= delay + 2 * driven.timestep + 1e-9
    # Then it accelerates at tau / I as if undelayed: the speed lags by the delay.
    w = driven.wheel_velocities()[0] - idle.wheel_velocities()[0]
    assert w == pytest.approx(2.0 * (100 * driven.timestep - delay) / 0.0075, rel=0.02)


def _balance_pitch(sim):
    """Return the pitch [rad] from which the robot, wheels on the floor, falls neither way."""
    lo, hi = -0.3, 0.3
    for _ in range(25):
        mid = 0.5 * (lo + hi)
        sim.reset('pitch', pitch=mid)
        sim.step(0.0, 0.0, 0.2)   # the hips' servos hold the legs as one rigid pendulum
        if sim.ground_truth()['theta'] > mid:   # fell forward: the balance is further back
            hi = mid
        else:
            lo = mid
    return 0.5 * (lo + hi)


@pytest.mark.parametrize('com_x', [-0.03, 0.04])
def test_the_body_leans_against_its_centre_of_mass(com_x):
    sim = RobotSim(body=_body(body_com=[com_x, 0.05]))
    pitch = _balance_pitch(sim)
    sim.place(pitch)
    p = sim.pendulum()
    # Balanced where the whole pendulum's centre of mass is over the axle ...
    assert pitch + p['offset'] == pytest.approx(0.0, abs=math.radians(0.05))
    # ... which is the default robot's, moved by the body's shift weighted by its share of
    # the pendulum's mass.
    ref = RobotSim()
    ref.place(pitch)
    r = ref.pendulum()
    dx, dz = r['l'] * math.sin(r['offset']), r['l'] * math.cos(r['offset'])
    expected = -math.atan2(dx + 11.0 * com_x / p['mass'], dz)
    assert pitch == pytest.approx(expected, abs=math.radians(0.2))


def test_a_heavier_higher_body_changes_the_pendulum():
    sim = RobotSim(body=_body(body_mass=15.4, body_com=[0.0, 0.10], body_inertia=0.1))
    sim.place(0.0)
    default = RobotSim()
    default.place(0.0)
    p, ref = sim.pendulum(), default.pendulum()
    body_l = default.ground_truth()['l']   # the default body's centre of mass above the axle
    assert p['mass'] - ref['mass'] == pytest.approx(4.4, abs=1e-9)
    # The body's centre of mass 5 cm higher, at 15.4 of the pendulum's kg.
    assert p['l'] * p['mass'] - ref['l'] * ref['mass'] == pytest.approx(
        15.4 * (body_l + 0.05) - 11.0 * body_l, abs=0.005)
    assert sim.ground_truth()['l'] == pytest.approx(body_l + 0.05, abs=1e-9)
    assert sim.model.body('base_link').inertia[1] == 0.1


@pytest.mark.parametrize('radius', [0.08, 0.12])
def test_the_wheel_radius_is_the_contact_and_the_rolling(radius):
    sim = RobotSim(body=_body(wheel_radius=radius, wheel_mass=1.5,
                              wheel_inertia=0.5 * 1.5 * radius ** 2))
    sim.place(0.0)
    axle = sim.data.xpos[sim.model.body('left_wheel').id][2]
    assert axle == pytest.approx(radius - CONTACT_DEPTH, abs=1e-6)
    sim.reset('tail')
    sim.step(1.0, 1.0, 0.3)   # rolls on the tail ...
    sim.step(0.0, 0.0, 0.1)   # ... and coasts (no tangential force: no slip in the soft contact)
    gt, w = sim.ground_truth(), sim.wheel_velocities()
    assert gt['x_dot'] > 0.1
    # Rolling on the axle's height above the floor: the radius less the soft contact's sink.
    rolling = sim.data.xpos[sim.model.body('left_wheel').id][2]
    assert radius - rolling < 0.01 * radius
    assert gt['x_dot'] == pytest.approx(rolling * (0.5 * (w[0] + w[1]) + gt['theta_dot']),
                                        rel=0.002)


def test_sim_node_takes_the_quantities_and_names_a_wrong_one():
    cfg = from_flat(SimConfig, {'robot.body_mass': 14.0, 'robot.motor_delay': 0.004})
    assert check(cfg) == []
    assert cfg.robot.body_mass == 14.0 and cfg.robot.motor_delay == 0.004
    for changes, words in (({'robot.body_mass': -1.0}, 'robot.body_mass = -1.0 is outside'),
                           ({'robot.body_com': [0.0]}, 'robot.body_com needs 2 entries'),
                           ({'robot.motor_delay': float('nan')}, 'robot.motor_delay must be')):
        with pytest.raises(ValueError) as err:
            from_flat(SimConfig, changes)
        assert words in str(err.value) and '\n' not in str(err.value)
    # A wheel heavier about its axle than its mass at the rim: the rule between them.
    problems = check(from_flat(SimConfig, {'robot.wheel_inertia': 0.05}))
    assert len(problems) == 1 and 'robot.wheel_inertia' in problems[0]
