"""
The ``identify`` command (identification/cli.py): a short --sim run, then --recording on its MCAP.

The --sim run plays short phases on a sim_node parameter file's variant and must write the
report, the fitted balance_node file, the plots and the recordings; its values are checked
against the variant's (looser than the issue's targets: the phases are short). --recording
then refits the MCAP files it wrote and must give the same values (the same samples).
"""
import json
import math

import pytest
from wheelleg_balance.identification import cli
import yaml

#: A variant unlike the default (sim_node ``robot.*``) and its IMU offset d [rad].
VARIANT = {'body_mass': 12.5, 'body_com': [-0.015, 0.05], 'wheel_mass': 1.5,
           'wheel_radius': 0.1, 'wheel_inertia': 0.0085, 'wheel_damping': 0.05,
           'motor_delay': 0.002}
D = math.radians(1.5)


@pytest.fixture(scope='module')
def sim_run(tmp_path_factory):
    """Run identify --sim --short on VARIANT: (exit code, output folder)."""
    folder = tmp_path_factory.mktemp('identify')
    params = folder / 'variant.yaml'
    params.write_text(yaml.safe_dump({'sim_node': {'ros__parameters': {
        'robot': VARIANT, 'imu_pitch_offset': D}}}))
    code = cli.main(['--sim', '--sim-params', str(params), '--output', str(folder / 'out'),
                     '--short'])
    return code, folder / 'out'


def test_sim_writes_the_report_the_file_and_the_plots(sim_run):
    code, out = sim_run
    assert code == 0
    report = json.loads((out / 'identify_report.json').read_text())
    assert report['phases'] == ['stand', 'tail', 'balance']
    assert report['sim_variant']['imu_pitch_offset'] == pytest.approx(D)
    q = {k: v['value'] for k, v in report['quantities'].items()}
    assert q['robot.wheel_radius'] == pytest.approx(VARIANT['wheel_radius'], rel=0.02)
    assert q['robot.wheel_inertia'] == pytest.approx(VARIANT['wheel_inertia'], rel=0.05)
    assert q['robot.motor_delay'] == pytest.approx(VARIANT['motor_delay'], abs=0.001)
    assert q['robot.body_mass'] == pytest.approx(VARIANT['body_mass'], rel=0.05)
    assert q['imu_pitch_offset'] == pytest.approx(D, abs=math.radians(0.1))
    # The report's comparison is against the variant the file asked for.
    assert report['simulator']['robot.body_mass']['true'] == VARIANT['body_mass']
    fitted = yaml.safe_load((out / 'fitted.yaml').read_text())['balance_node']['ros__parameters']
    assert fitted['wheel_radius'] == pytest.approx(q['robot.wheel_radius'])
    assert fitted['lift_wheel_inertia'] == pytest.approx(q['robot.wheel_inertia'])
    for phase in ('stand', 'tail', 'balance'):
        assert (out / ('identify_%s.png' % phase)).stat().st_size > 10000
        assert (out / 'recordings' / ('%s.mcap' % phase)).stat().st_size > 0


def test_recording_refits_the_mcap_files_to_the_same_values(sim_run, tmp_path):
    pytest.importorskip('mcap.reader')
    code, out = sim_run
    assert code == 0
    target = tmp_path / 'fitted.yaml'
    assert cli.main(['--recording', str(out / 'recordings'), '--output', str(target)]) == 0
    ours = json.loads((out / 'identify_report.json').read_text())['quantities']
    theirs = json.loads((tmp_path / 'identify_report.json').read_text())['quantities']
    assert set(theirs) == set(ours)
    for name in ('robot.body_mass', 'robot.wheel_radius', 'robot.wheel_inertia',
                 'robot.motor_delay', 'imu_pitch_offset'):
        assert theirs[name]['value'] == pytest.approx(ours[name]['value'], rel=1e-5)
    assert (tmp_path / 'identify_balance.png').exists()
    a = yaml.safe_load(target.read_text())['balance_node']['ros__parameters']
    b = yaml.safe_load((out / 'fitted.yaml').read_text())['balance_node']['ros__parameters']
    assert a['body_mass'] == pytest.approx(b['body_mass'], rel=1e-5)


def test_recording_of_one_phase_by_window_reports_and_writes_no_file(
        sim_run, tmp_path, capsys):
    pytest.importorskip('mcap.reader')
    code, out = sim_run
    target = tmp_path / 'fitted.yaml'
    code = cli.main(['--recording', str(out / 'recordings' / 'stand.mcap'),
                     '--window', 'stand=0:1.0', '--output', str(target)])
    assert code == 1   # only the stand: no fitted file
    assert not target.exists()
    report = json.loads((tmp_path / 'identify_report.json').read_text())
    assert report['phases'] == ['stand']
    assert report['quantities']['robot.motor_delay']['value'] == pytest.approx(
        VARIANT['motor_delay'], abs=0.001)
    assert 'tail, balance missing' in capsys.readouterr().err


def test_recording_names_what_is_wrong(tmp_path, capsys):
    (tmp_path / 'walk.mcap').write_bytes(b'')
    assert cli.main(['--recording', str(tmp_path), '--output', str(tmp_path / 'f.yaml')]) == 1
    assert 'does not start with a phase' in capsys.readouterr().err
    assert cli.main(['--recording', str(tmp_path / 'walk.mcap'), '--window', 'walk=0:1',
                     '--output', str(tmp_path / 'f.yaml')]) == 1
    assert 'PHASE=START:END' in capsys.readouterr().err


def test_the_config_gives_the_leg_geometry(tmp_path):
    path = tmp_path / 'robot.yaml'
    path.write_text(yaml.safe_dump({'balance_node': {'ros__parameters': {
        'leg': {'thigh': 0.16}}}}))
    assert cli.leg_of(str(path)).thigh == pytest.approx(0.16)
    assert cli.leg_of(None).thigh != pytest.approx(0.16)
