"""identification/leg_study.py: the stiffer legs are in the simulated model, and only inside."""
import mujoco
import pytest
from wheelleg_balance.identification.leg_study import stiff_legs
from wheelleg_balance.sim.robot_sim import RobotSim


def _legs(sim):
    m = sim.model
    closure = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, 'left_closure')
    servo = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, 'left_leg_front_servo')
    return (float(m.eq_solref[closure][0]), float(m.actuator_gainprm[servo][0]),
            float(m.actuator_biasprm[servo][1]), float(m.actuator_biasprm[servo][2]))


def test_stiff_legs_changes_the_model_inside_the_block_only():
    before = _legs(RobotSim())
    assert before == pytest.approx((0.004, 3000.0, -3000.0, -60.0))
    with stiff_legs(0.001, 30000.0, 300.0):
        inside = _legs(RobotSim())
    assert inside == pytest.approx((0.001, 30000.0, -30000.0, -300.0))
    assert _legs(RobotSim()) == before
