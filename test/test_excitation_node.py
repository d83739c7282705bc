"""
balance_node's excitation mode through its services (core/excitation.py in the control loop).

The faults rig (validation/faults/rig.py: balance_node, fake MIT motors on a virtual bus, the
sensors over DDS) with the MuJoCo robot on a stand: ``~/excite/<phase>`` is answered with the
loop's reply (a refusal with its reason, the stand's after its probe), ~/state and
/diagnostics carry the phase, ``~/stop`` ends it with zero torque on the bus at once.
"""
import time

import pytest
from std_srvs.srv import Trigger

from wheelleg_balance.core.excitation import PHASE_INDEX, STAND_MAX_SPEED
from wheelleg_balance.validation.faults.bench import IDX
from wheelleg_balance.validation.faults.plants import MujocoPlant
from wheelleg_balance.validation.faults.rig import Rig, SLACK, wait_for

pytestmark = pytest.mark.ros


def test_excite_services_refuse_play_and_stop(context):
    plant = MujocoPlant(pose='tail')
    plant.sim.hold(pitch=0.0, z=1.0)   # on a stand: the wheels free
    # the wheel speeds from the plant's joint states (the fake motors know only the torque)
    with Rig(context, plant=plant, wheel_state_source='joint_states') as rig:
        robot = rig.robot
        ns = rig.node.get_namespace()
        clients = {phase: robot.create_client(Trigger, '%s/balance_node/excite/%s'
                                              % (ns, phase)) for phase in PHASE_INDEX}
        assert wait_for(lambda: robot.last_state() is not None
                        and all(c.service_is_ready() for c in clients.values()), 10.0)
        answer = robot.call(clients['balance'], Trigger.Request())
        assert not answer.success and 'needs the robot balancing' in answer.message
        # the sensors and the motors' replies reached the loop: nothing refuses a phase
        assert wait_for(lambda: robot.safety().get('conditions') == '', 10.0)
        answer = robot.call(clients['stand'], Trigger.Request())
        assert answer.success, answer.message
        assert robot.wait_mode('EXCITING', 1.0) is not None
        assert wait_for(lambda: robot.last_state()[IDX['excitation']] == PHASE_INDEX['stand'],
                        1.0)
        assert wait_for(lambda: robot.safety().get('excitation') == 'stand', 2.0)
        time.sleep(0.5)
        assert max(abs(t) for t in rig.motors.wheel_torques()) > 0.0
        stopped = time.time()
        assert robot.call(robot.create_client(Trigger, '%s/balance_node/stop' % ns),
                          Trigger.Request()).success
        limit = rig.params['motor_timeout'] + SLACK
        assert wait_for(lambda: max(abs(t) for t in rig.motors.wheel_torques()) == 0.0, limit)
        assert robot.wait_mode('DISARMED', 1.0) is not None
        assert time.time() - stopped < 1.0
        assert max(abs(v) for v in plant.sim.wheel_velocities()) < STAND_MAX_SPEED
