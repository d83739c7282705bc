"""``tuning --config --sim-params``: the runs and cores are the identified robot's."""
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.validation.paper import tuning
import yaml

FITTED = {'body_mass': 15.6, 'wheel_mass': 3.85, 'wheel_radius': 0.12}
BODY = {'body_mass': 15.4, 'wheel_radius': 0.12, 'wheel_mass': 1.8, 'wheel_inertia': 0.0115}


def _robot(tmp_path):
    fitted = tmp_path / 'fitted.yaml'
    fitted.write_text(yaml.safe_dump({'balance_node': {'ros__parameters': FITTED}}))
    sim = tmp_path / 'variant.yaml'
    sim.write_text(yaml.safe_dump({'sim_node': {'ros__parameters': {'robot': BODY}}}))
    return tuning.robot_of([str(fitted)], str(sim))


def test_the_robot_of_the_files(tmp_path):
    robot = _robot(tmp_path)
    assert robot.model.body_mass == FITTED['body_mass']
    assert robot.model.wheel_radius == FITTED['wheel_radius']
    assert dict(robot.params) == FITTED
    assert robot.body.body_mass == BODY['body_mass']
    assert robot.body.wheel_inertia == BODY['wheel_inertia']


def test_every_run_and_core_simulates_the_robot(tmp_path):
    robot = _robot(tmp_path)
    for plant in tuning.PLANTS:
        for run in tuning.scenarios(quick=True, plant=plant, robot=robot):
            if run.play is not None:
                assert run.play.body == robot.body
                assert set(FITTED.items()) <= set(run.play.params)
            else:
                assert run.scenario.params == robot.model
    core = tuning.make_core(tuning.START, robot.model)
    assert core.p.body_mass == FITTED['body_mass']
    assert tuning.make_core(tuning.START).p == RobotParams()
