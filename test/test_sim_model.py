"""
The MuJoCo robot (sim/robot.xml behind sim/robot_sim.py) against DESIGN.md section 1.

Masses and geometry, the rest on the tail, the IMU offset, the sign conventions of wheel torque
and of the encoders (relative to the leg), the height servo and the scenario features.
"""
import math

from hypothesis import given, settings, strategies as st
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from wheelleg_balance.core.estimation import pitch_from_quaternion
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.sim.robot_sim import CONTACT_DEPTH, Push, RobotSim, Slope, WHEEL_RADIUS

G = 9.81


def _run(sim, seconds, tau_left=0.0, tau_right=0.0):
    sim.step(tau_left, tau_right, seconds)
    return sim.ground_truth()


def _contacts(sim):
    m, d = sim.model, sim.data
    return {m.geom(c.geom2).name for c in d.contact[:d.ncon] if m.geom(c.geom1).name == 'floor'}


def test_masses_and_geometry_match_the_design():
    sim = RobotSim()
    m = sim.model
    assert m.body('base_link').mass[0] == pytest.approx(11.0)
    for side in ('left', 'right'):
        assert m.body(side + '_wheel').mass[0] == pytest.approx(1.5)
        assert m.geom(side + '_wheel').size[0] == pytest.approx(WHEEL_RADIUS)
    # Everything else (leg links, tail wheel) is light: under 5 % of the body.
    rest = m.body_mass.sum() - 11.0 - 3.0
    assert 0.0 < rest < 0.05 * 11.0
    sim.place(0.0)
    left, right = (sim.data.xpos[m.body(n).id] for n in ('left_wheel', 'right_wheel'))
    assert left[1] - right[1] == pytest.approx(0.47)
    for z in (left[2], right[2]):   # axle at r_w, less the soft contact's resting depth
        assert z == pytest.approx(WHEEL_RADIUS - CONTACT_DEPTH)
    assert m.opt.timestep == 0.0005
    # The leg links are core/kinematics.py's default five-bar.
    leg = FiveBarLeg()
    assert m.body('left_front_shank').pos[0] == pytest.approx(leg.thigh)
    assert m.body('left_wheel').pos[0] == pytest.approx(leg.shank)
    assert m.body('left_front_thigh').pos[0] - m.body('left_rear_thigh').pos[0] == \
        pytest.approx(leg.hip_spacing)
    assert m.body_ipos[m.body('base_link').id][2] == pytest.approx(leg.com_height)
    # Wheel motors: torque actuators limited to +-18 N m.
    for name in ('left_wheel', 'right_wheel'):
        assert list(m.actuator(name).ctrlrange) == [-18.0, 18.0]


def test_zero_torque_falls_forward_onto_the_tail_and_rests_at_36_deg():
    sim = RobotSim()
    sim.reset('pitch', pitch=math.radians(5.0))
    gt = _run(sim, 3.0)
    assert math.degrees(gt['theta']) == pytest.approx(36.0, abs=3.0)
    assert abs(gt['theta_dot']) < 1e-3 and abs(gt['x_dot']) < 0.01
    assert {'tail_wheel', 'left_wheel', 'right_wheel'} <= _contacts(sim)
    # The geometric rest pitch agrees, and reset('tail') starts there, settled.
    assert math.degrees(sim.tail_rest_pitch()) == pytest.approx(36.0, abs=3.0)
    sim.reset('tail')
    assert sim.ground_truth()['theta'] == pytest.approx(gt['theta'], abs=math.radians(0.5))
    assert abs(sim.ground_truth()['theta_dot']) < 1e-3


@settings(max_examples=8, deadline=None)
@given(d=st.floats(-0.1, 0.1), pitch=st.floats(-0.3, 0.3))
def test_imu_reads_pitch_plus_offset_on_the_stand(d, pitch):
    sim = RobotSim(d_offset=d)
    sim.hold(pitch)
    sim.step(0.0, 0.0, 0.1)
    quat, gyro, accel = sim.imu()
    true_pitch = sim.ground_truth()['theta']
    assert true_pitch == pytest.approx(pitch, abs=1e-4)  # the stand holds
    assert pitch_from_quaternion(*quat) == pytest.approx(true_pitch + d, abs=1e-4)
    assert np.allclose(gyro, 0.0, atol=1e-2)
    # At rest the accelerometer sees gravity's reaction, up in the world, in the IMU frame.
    a = pitch + d
    assert accel[0] == pytest.approx(-G * math.sin(a), abs=0.05)
    assert accel[1] == pytest.approx(0.0, abs=0.05)
    assert accel[2] == pytest.approx(G * math.cos(a), abs=0.05)


def test_imu_offset_level_body():
    d = math.radians(2.2)
    sim = RobotSim(d_offset=d)
    sim.hold(0.0)
    sim.step(0.0, 0.0, 0.2)
    assert pitch_from_quaternion(*sim.imu()[0]) == pytest.approx(d, abs=2e-4)
    sim.set_imu_offset(0.0)
    assert pitch_from_quaternion(*sim.imu()[0]) == pytest.approx(0.0, abs=2e-4)


def test_positive_wheel_torque_drives_forward_and_pitches_the_body_back():
    sim = RobotSim()
    gt0 = sim.ground_truth()
    gt = _run(sim, 0.3, 2.0, 2.0)
    assert gt['x'] > gt0['x'] + 0.05 and gt['x_dot'] > 0.2
    wl, wr = sim.wheel_velocities()
    assert wl > 2.0 and wr == pytest.approx(wl, rel=1e-6)   # forward-positive encoders
    assert abs(gt['yaw']) < 1e-6
    # Enough torque lifts the body off the tail: the reaction pitches it backwards.
    sim = RobotSim()
    gt = _run(sim, 0.15, 15.0, 15.0)
    assert gt['theta_dot'] < -1.0 and gt['theta'] < sim.tail_rest_pitch() - 0.05
    assert 'tail_wheel' not in _contacts(sim)


def test_more_left_torque_turns_right():
    sim = RobotSim()
    gt = _run(sim, 0.5, 1.0, -1.0)
    assert gt['yaw_rate'] < -0.01 and gt['yaw'] < -0.005


def test_encoders_measure_the_wheel_relative_to_the_leg():
    """x_dot = r_w ((w_l + w_r)/2 + theta_dot) (core/estimation.py), not r_w (w_l + w_r)/2."""
    sim = RobotSim()
    sim.reset('pitch', pitch=0.05)
    worst = paper_worst = 0.0
    for _ in range(150):  # 0.3 s of falling forward with free wheels: fast pitching
        gt = _run(sim, 0.002)
        w = 0.5 * sum(sim.wheel_velocities())
        worst = max(worst, abs(WHEEL_RADIUS * (w + gt['theta_dot']) - gt['x_dot']))
        paper_worst = max(paper_worst, abs(WHEEL_RADIUS * w - gt['x_dot']))
    assert gt['theta_dot'] > 2.0 and 'tail_wheel' not in _contacts(sim)
    assert worst < 0.01
    assert paper_worst > 0.15


def _pendulum_on_wheels(p, tau_total, y0, horizon, reaction=True, wheels=True):
    """
    Wheeled inverted pendulum (Lagrange, rolling without slip), y = [theta, theta_dot, x, x_dot].

    (M_w + I_w / r_w^2 + m) x_dd + m l cos(theta) theta_dd - m l sin(theta) theta_dot^2 = tau / r_w
    m l cos(theta) x_dd + (m l^2 + I_b) theta_dd - m g l sin(theta) = -tau
    with tau the total wheel torque, whose reaction turns the body. Without the reaction torque,
    wheel inertia and body inertia this is the paper's model (1) with u = tau / r_w.
    """
    m, l = p['mass'], p['l']
    cart = p['wheel_mass'] + (p['wheel_inertia'] / WHEEL_RADIUS ** 2 if wheels else 0.0)
    i_b = p['inertia'] if reaction else 0.0

    def f(t, y):
        th, thd = y[0], y[1]
        c, s = math.cos(th), math.sin(th)
        mass = np.array([[cart + m, m * l * c], [m * l * c, m * l * l + i_b]])
        rhs = np.array([tau_total / WHEEL_RADIUS + m * l * s * thd * thd,
                        m * G * l * s - (tau_total if reaction else 0.0)])
        x_dd, th_dd = np.linalg.solve(mass, rhs)
        return [thd, th_dd, y[3], x_dd]

    return solve_ivp(f, (0.0, horizon), y0, rtol=1e-9, atol=1e-12).y[:, -1]


@pytest.mark.parametrize('theta0,tau', [(0.05, 1.0), (0.0, -2.0), (0.0, 1.5), (0.1, 0.0)])
def test_dynamics_follow_the_wheeled_pendulum_not_quite_model_1(theta0, tau):
    """
    The simulated robot obeys the wheeled inverted pendulum with its own mass properties.

    Over 0.15 s of open loop (the motion is unstable: errors grow e-fold every ~0.1 s) theta
    and x agree within 3 % of their change. The paper's model (1) leaves out the reaction
    torque on the body and the wheel and body inertias: it is off by more than that when a
    torque acts (the controllers have to live with the difference).
    """
    sim = RobotSim()
    sim.reset('pitch', pitch=theta0)
    p = sim.pendulum()
    gt0 = sim.ground_truth()
    y0 = [gt0['theta'] + p['offset'], 0.0, gt0['x'], 0.0]
    horizon = 0.15
    sim.step(tau, tau, horizon)
    gt = sim.ground_truth()
    theta, x = gt['theta'] + p['offset'], gt['x']
    wip = _pendulum_on_wheels(p, 2.0 * tau, y0, horizon)
    d_theta, d_x = abs(wip[0] - y0[0]), abs(wip[2] - y0[2])
    assert theta == pytest.approx(wip[0], abs=0.03 * d_theta + 2e-3)
    assert x == pytest.approx(wip[2], abs=0.03 * d_x + 1e-3)
    if tau != 0.0:
        model_1 = _pendulum_on_wheels(p, 2.0 * tau, y0, horizon, reaction=False, wheels=False)
        assert abs(model_1[0] - theta) > 0.05 * d_theta


@pytest.mark.parametrize('target', [0.45, 0.60, 0.70])
def test_commanded_height_is_reached(target):
    sim = RobotSim()
    sim.hold(0.0, z=1.0)      # on the stand, wheels in the air
    sim.set_height(target)
    sim.step(0.0, 0.0, 1.0)
    leg = sim.leg
    q = sim.leg_angles()
    assert sim.ground_truth()['l'] == pytest.approx(target, abs=0.005)
    assert leg.height(q[0], q[1]) == pytest.approx(target, abs=0.005)
    assert leg.height(q[2], q[3]) == pytest.approx(target, abs=0.005)


def test_push_moves_the_robot_only_while_it_acts():
    sim = RobotSim(pushes=[Push(start=0.2, duration=0.2, force_x=-40.0)])
    gt = _run(sim, 0.19)
    assert abs(gt['x_dot']) < 0.01
    gt = _run(sim, 0.21)
    assert gt['x_dot'] < -0.3
    after = _run(sim, 0.1)['x_dot']
    assert not sim.data.xfrc_applied.any()
    assert _run(sim, 0.1)['x_dot'] == pytest.approx(after, abs=0.05)  # coasting, not pushed


def test_bump_lifts_the_wheels_by_its_height():
    sim = RobotSim(bumps=[0.3], bump_height=0.02)
    top = 0.0
    for _ in range(700):
        sim.step(1.0, 1.0, 0.002)
        top = max(top, float(np.mean([sim.data.xpos[b][2] for b in sim._wheels])))
    assert sim.ground_truth()['x'] > 0.5     # drove over it
    assert top == pytest.approx(WHEEL_RADIUS + 0.02, abs=0.005)


def test_slope_lifts_the_left_wheel_only():
    start = 0.2
    sim = RobotSim(slope=Slope(start_x=start))
    checked = 0
    for _ in range(1000):
        sim.step(1.0, 1.0, 0.002)
        gt = sim.ground_truth()
        if start + 0.15 < gt['x'] < start + 0.45:
            z_left, z_right = (sim.data.xpos[b][2] for b in sim._wheels)
            ramp = (gt['x'] - start) * math.tan(math.radians(7.0))
            assert z_left - WHEEL_RADIUS == pytest.approx(ramp, abs=0.01)
            assert z_right == pytest.approx(WHEEL_RADIUS, abs=0.002)
            assert gt['roll'] > 0.0    # left side up is a positive roll (REP 103)
            checked += 1
    assert checked > 10


def test_deterministic():
    runs = []
    for _ in range(2):
        sim = RobotSim(d_offset=0.03, pushes=[Push(0.1, 0.1, 20.0)], bumps=[0.2])
        for k in range(300):
            sim.step(3.0 * math.sin(0.05 * k), 2.0, 0.002)
        runs.append(np.concatenate([sim.data.qpos, sim.data.qvel, sim.data.sensordata]))
    assert np.array_equal(runs[0], runs[1])


def test_non_finite_torque_is_zero_and_limits_hold():
    sim = RobotSim()
    sim.step(float('nan'), float('inf'), 0.002)
    assert sim.wheel_torques() == (0.0, 0.0)
    sim.step(100.0, -100.0, 0.002)
    assert sim.wheel_torques() == (18.0, -18.0)
    with pytest.raises(ValueError):
        sim.set_height(0.9)   # beyond the legs' reach


# ---- hips driven by torque (legs='motors') -------------------------------------------------

def test_hip_torque_motors_carry_the_body_and_follow_the_sign_convention():
    from wheelleg_balance.sim.robot_sim import HIP_TORQUE_LIMIT
    sim = RobotSim(legs='motors')
    sim.reset('tail')
    assert sim.ground_truth()['l'] == pytest.approx(0.37, abs=0.005)   # settled, held
    sim.reset('pitch', pitch=0.0)
    sim.step(0.0, 0.0, 0.2, hip_torques=(0.0,) * 4)
    assert sim.ground_truth()['l'] < 0.30      # upright on its wheels, unpowered: it sinks
    sim.reset('pitch', pitch=0.0)
    tau = sim.leg.static_torques(*sim.leg.inverse(0.37), 11.45 * G / 2.0)
    sim.step(0.0, 0.0, 0.2, hip_torques=tau + tau)
    assert sim.ground_truth()['l'] == pytest.approx(0.37, abs=0.01)   # J^T f carries it
    # On the stand, a positive torque turns every hip's q up (the leg extends).
    sim = RobotSim(legs='motors', height=0.45)
    sim.hold(0.0, z=1.0)
    q0 = sim.leg_angles()
    sim.step(0.0, 0.0, 0.1, hip_torques=(3.0,) * 4)
    assert all(q > a + 0.05 for q, a in zip(sim.leg_angles(), q0))
    sim.step(0.0, 0.0, 0.002, hip_torques=(100.0, -100.0, math.nan, 1.0))
    assert sim.leg_torques() == (HIP_TORQUE_LIMIT, -HIP_TORQUE_LIMIT, 0.0, 1.0)


def test_servo_mode_ignores_hip_torques():
    sim = RobotSim()
    sim.hold(0.0, z=1.0)
    sim.step(0.0, 0.0, 0.5, hip_torques=(18.0,) * 4)
    assert sim.ground_truth()['l'] == pytest.approx(0.37, abs=0.005)
    with pytest.raises(ValueError):
        RobotSim(legs='knees')


def test_folded_pose_rests_on_the_tail_with_limp_legs_on_their_stops():
    sim = RobotSim(legs='motors')
    sim.reset('folded')
    gt = sim.ground_truth()
    assert all(q == pytest.approx(sim.leg.q_min, abs=0.02) for q in sim.leg_angles())
    assert gt['l'] < 0.30 and gt['tail_contact'] == 1.0 and gt['body_contact'] == 0.0
    assert 0.1 < gt['theta'] < 0.3          # the folded rest: about 10 deg
    sim.step(0.0, 0.0, 0.5, hip_torques=(0.0,) * 4)
    assert sim.ground_truth()['theta'] == pytest.approx(gt['theta'], abs=1e-3)   # settled
    with pytest.raises(ValueError):
        RobotSim().reset('folded')          # the servos would hold the legs


def test_contact_fields_show_what_touches_the_floor():
    sim = RobotSim()
    sim.reset('tail')
    assert sim.ground_truth()['tail_contact'] == 1.0
    sim.reset('pitch', pitch=0.0)
    assert sim.ground_truth()['tail_contact'] == 0.0
    sim.reset('pitch', pitch=-0.3)          # unpowered, it falls backwards onto the body
    for _ in range(1000):
        sim.step(0.0, 0.0, 0.002)
        if sim.ground_truth()['body_contact']:
            break
    gt = sim.ground_truth()
    assert gt['body_contact'] == 1.0 and gt['tail_contact'] == 0.0 and gt['theta'] < -0.5


def test_robot_motors_route_frames_by_bus_and_id_and_evaluate_every_step():
    from wheelleg_balance.core.protocols.mit import MitProtocol
    from wheelleg_balance.sim.robot_motors import default_specs, RobotMotors
    mit = MitProtocol()
    sim = RobotSim(legs='motors', height=0.45)
    sim.hold(0.0, z=1.0)
    motors = RobotMotors(sim, default_specs(hip_bus=1))
    assert motors.handle(mit.enable_frames([3])[0], bus=0) is None    # hips on bus 1
    assert motors.handle(mit.enable_frames([1])[0], bus=0) is not None
    q = sim.leg_angles()
    # Stiff holds of the left hips at their present angles: the impedance law, evaluated at
    # each 0.5 ms step, keeps them there against the hanging wheel; the right leg swings.
    for i, q_i in zip((3, 4), q):
        assert motors.handle(mit.enable_frames([i])[0], bus=1) is not None
        assert motors.handle(mit.command_frame(i, q_i, 0.0, 200.0, 2.0, 0.0), bus=1)
    motors.step(0.5)
    # Within the droop of the hanging wheel (about 3 N m per hip over kp 200: 16 mrad).
    assert sim.leg_angles()[:2] == pytest.approx(q[:2], abs=0.025)
    assert abs(sim.leg_angles()[2] - q[2]) > 0.05
    with pytest.raises(ValueError):
        RobotMotors(RobotSim(), default_specs())       # hip motors need legs='motors'


@pytest.mark.parametrize('hip_bus', [0, 1])
def test_lockstep_waits_for_the_frames_that_close_a_tick(hip_bus):
    """
    The lockstep waits for the frames that close a tick (RobotMotors.commanded).

    On one bus the wheels close a tick, whichever hips it commanded (in turns,
    legs.command_divider; they are sent before the wheels); hips on their own bus are waited
    for each; with no wheel in motor mode, every enabled motor is.
    """
    from wheelleg_balance.core.protocols.mit import MitProtocol
    from wheelleg_balance.sim.robot_motors import default_specs, RobotMotors
    mit = MitProtocol()
    sim = RobotSim(legs='motors', height=0.45)
    motors = RobotMotors(sim, default_specs(hip_bus=hip_bus))

    def send(ids, bus):
        for i in ids:
            motors.handle(mit.command_frame(i, 0.0, 0.0, 0.0, 1.0, 0.0), bus=bus)

    for i in (3, 4, 5, 6):   # a hip enabled alone (bringup): it is waited for
        motors.handle(mit.enable_frames([i])[0], bus=hip_bus)
    marks = motors.command_marks()
    assert not motors.commanded(marks)
    send((3, 4, 5, 6), hip_bus)
    assert motors.commanded(marks)
    for i in (1, 2):
        motors.handle(mit.enable_frames([i])[0], bus=0)
    marks = motors.command_marks()
    send((3, 4), hip_bus)            # the left leg's turn
    assert not motors.commanded(marks)
    send((1,), 0)
    assert not motors.commanded(marks)
    send((2,), 0)                    # the wheels close the tick on one bus
    assert motors.commanded(marks) is (hip_bus == 0)
    send((5, 6), hip_bus)            # on a bus of their own every hip is waited for
    assert motors.commanded(marks)
