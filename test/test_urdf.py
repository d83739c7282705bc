"""
urdf/wheelleg_balance.urdf against the MuJoCo model sim/robot.xml and core/kinematics.py.

Forward kinematics of the URDF is computed here with numpy from its joint origins and axes (the
URDF convention: child pose = parent * origin(xyz, rpy) * rotation(axis, q)), so these tests
check the file robot_state_publisher reads, not a model of it.
"""
import math
import pathlib
import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from wheelleg_balance.core.frames import base_footprint_to_base_link
from wheelleg_balance.core.kinematics import FiveBarLeg
from wheelleg_balance.core.params import RobotParams
from wheelleg_balance.sim.robot_sim import CONTACT_DEPTH, MODEL_PATH, RobotSim, WHEEL_RADIUS

REPO = pathlib.Path(__file__).resolve().parents[1]
URDF_PATH = REPO / 'urdf' / 'wheelleg_balance.urdf'
LEG = FiveBarLeg()
SIDES = ('left', 'right')
# Hip angles over the joint range, symmetric and not, that the legs can reach.
HIP_GRID = [(qf, qr) for qf in np.linspace(LEG.q_min, LEG.q_max, 10)
            for qr in np.linspace(LEG.q_min, LEG.q_max, 10) if LEG.in_reach(qf, qr)]


def _floats(text, default='0 0 0'):
    return np.array([float(v) for v in (text or default).split()])


class Urdf:
    """The URDF's tree: joints by child link, forward kinematics from base_link."""

    def __init__(self, path=URDF_PATH):
        self.root = ET.parse(path).getroot()
        self.joints = {}
        for j in self.root.findall('joint'):
            origin = j.find('origin')
            axis = j.find('axis')
            self.joints[j.find('child').get('link')] = {
                'name': j.get('name'), 'type': j.get('type'),
                'parent': j.find('parent').get('link'),
                'xyz': _floats(origin.get('xyz') if origin is not None else None),
                'rpy': _floats(origin.get('rpy') if origin is not None else None),
                'axis': _floats(axis.get('xyz') if axis is not None else None, '1 0 0'),
                'limit': j.find('limit')}
        self.links = {link.get('name'): link for link in self.root.findall('link')}

    def joint(self, name):
        return next(j for j in self.joints.values() if j['name'] == name)

    def pose(self, link, q):
        """4x4 pose of link in base_link for joint positions q (dict by joint name)."""
        t = np.eye(4)
        while link != 'base_link':
            j = self.joints[link]
            local = np.eye(4)
            local[:3, :3] = Rotation.from_euler('xyz', j['rpy']).as_matrix()  # fixed axes
            local[:3, 3] = j['xyz']
            if j['type'] in ('revolute', 'continuous'):
                move = np.eye(4)
                move[:3, :3] = Rotation.from_rotvec(j['axis'] * q[j['name']]).as_matrix()
                local = local @ move
            t = local @ t
            link = j['parent']
        return t

    def mass(self, link):
        m = self.links[link].find('inertial/mass')
        return 0.0 if m is None else float(m.get('value'))


URDF = Urdf()


def _joint_positions(q_front, q_rear):
    k_f, k_r = LEG.knee_angles(q_front, q_rear)
    q = {}
    for side in SIDES:
        q.update({side + '_leg_front_joint': q_front, side + '_leg_rear_joint': q_rear,
                  side + '_front_knee': k_f, side + '_rear_knee': k_r, side + '_wheel_joint': 0.3})
    return q


# ---- the tree ------------------------------------------------------------------------------

def test_one_tree_rooted_at_base_link_with_the_named_links():
    children = set(URDF.joints)
    roots = set(URDF.links) - children
    assert roots == {'base_link'}
    for side in SIDES:
        for part in ('front_thigh', 'front_shank', 'rear_thigh', 'rear_shank', 'rear_shank_end'):
            assert side + '_' + part in URDF.links
        assert URDF.joints[side + '_wheel']['type'] == 'continuous'
        assert URDF.joints[side + '_front_shank']['parent'] == side + '_front_thigh'
        assert URDF.joints[side + '_wheel']['parent'] == side + '_front_shank'
    assert {'imu_link', 'tail', 'body'} <= set(URDF.links)
    # base_footprint is balance_node's (a fixed URDF joint could not follow pitch and height).
    assert 'base_footprint' not in URDF.links
    # KDL cannot give the root an inertia.
    assert URDF.links['base_link'].find('inertial') is None


@pytest.mark.parametrize('q_front,q_rear', HIP_GRID)
def test_chains_close_at_the_five_bar_axle(q_front, q_rear):
    q = _joint_positions(q_front, q_rear)
    xc, zc = LEG.axle(q_front, q_rear)
    for side, y in zip(SIDES, (1.0, -1.0)):
        wheel = URDF.pose(side + '_wheel', q)[:3, 3]
        rear_end = URDF.pose(side + '_rear_shank_end', q)[:3, 3]
        assert rear_end[[0, 2]] == pytest.approx([xc, zc], abs=1e-9)
        assert wheel[[0, 2]] == pytest.approx([xc, zc], abs=1e-9)
        # Rear shank in the leg plane, wheel outboard of it on the track.
        assert rear_end[1] == pytest.approx(0.19 * y, abs=1e-12)
        assert wheel[1] == pytest.approx(0.5 * RobotParams().wheel_separation * y, abs=1e-12)


def test_wheel_axle_stays_along_y_whatever_the_leg_angles():
    for q_front, q_rear in HIP_GRID[::7]:
        pose = URDF.pose('left_wheel', _joint_positions(q_front, q_rear))
        assert pose[:3, :3] @ URDF.joint('left_wheel_joint')['axis'] == \
            pytest.approx([0.0, 1.0, 0.0], abs=1e-12)


def test_knee_angles_over_the_hip_range_are_within_the_urdf_limits():
    knees = np.array([LEG.knee_angles(qf, qr) for qf, qr in HIP_GRID])
    for side in SIDES:
        for i, part in enumerate(('front', 'rear')):
            lim = URDF.joint('%s_%s_knee' % (side, part))['limit']
            lo, hi = float(lim.get('lower')), float(lim.get('upper'))
            assert lo < knees[:, i].min() and knees[:, i].max() < hi


# ---- the same numbers as robot.xml ---------------------------------------------------------

@pytest.fixture(scope='module')
def model():
    return mujoco.MjModel.from_xml_path(str(MODEL_PATH))


def test_joints_match_robot_xml(model):
    names = [side + s for side in SIDES for s in (
        '_leg_front_joint', '_leg_rear_joint', '_front_knee', '_rear_knee', '_wheel_joint')]
    for name in names:
        j = URDF.joint(name)
        mj = model.joint(name)
        assert j['xyz'] == pytest.approx(model.body_pos[mj.bodyid[0]], abs=1e-12), name
        assert j['rpy'] == pytest.approx([0.0, 0.0, 0.0]), name
        assert j['axis'] == pytest.approx(mj.axis, abs=1e-12), name
        if 'leg' in name:
            lim = j['limit']
            assert [float(lim.get('lower')), float(lim.get('upper'))] == \
                pytest.approx(mj.range), name
            act = model.actuator(name.replace('_joint', ''))   # the hip's torque motor
            assert float(lim.get('effort')) == pytest.approx(act.ctrlrange[1]), name
    wheel = model.actuator('left_wheel')
    assert float(URDF.joint('left_wheel_joint')['limit'].get('effort')) == \
        pytest.approx(wheel.ctrlrange[1])


def test_frames_and_masses_match_robot_xml(model):
    m = model
    # IMU, tail wheel and the rear shank ends where robot.xml has them.
    zero = _joint_positions(0.5, 0.5)
    assert URDF.pose('imu_link', zero)[:3, 3] == pytest.approx(m.site('imu').pos)
    assert URDF.pose('imu_link', zero)[:3, :3] == pytest.approx(np.eye(3))
    tail = URDF.pose('tail', zero)
    tail_com = tail[:3, :3] @ _floats(URDF.links['tail'].find('inertial/origin').get('xyz')) \
        + tail[:3, 3]
    assert tail_com == pytest.approx(m.body('tail_wheel').pos, abs=1e-12)
    for side in SIDES:
        assert URDF.joints[side + '_rear_shank_end']['xyz'] == \
            pytest.approx(m.site(side + '_rear_end').pos, abs=1e-12)
    # Masses, centres of mass and principal inertias link by link.
    pairs = {'body': 'base_link', 'tail': 'tail_wheel'}
    for side in SIDES:
        for part in ('front_thigh', 'front_shank', 'rear_thigh', 'rear_shank', 'wheel'):
            pairs[side + '_' + part] = side + '_' + part
    total = 0.0
    for link, body in pairs.items():
        b = m.body(body)
        inertial = URDF.links[link].find('inertial')
        assert URDF.mass(link) == pytest.approx(b.mass[0]), link
        inertia = inertial.find('inertia')
        diag = sorted(float(inertia.get(k)) for k in ('ixx', 'iyy', 'izz'))
        assert diag == pytest.approx(sorted(b.inertia), rel=1e-6), link
        if link not in ('body', 'tail'):
            assert _floats(inertial.find('origin').get('xyz')) == \
                pytest.approx(b.ipos, abs=1e-12), link
        total += URDF.mass(link)
    robot = sum(m.body_mass[1:]) - m.body('stand').mass[0]
    assert total == pytest.approx(robot)
    assert URDF.pose('body', zero)[:3, 3] == pytest.approx(m.body('base_link').ipos)


def test_shapes_match_robot_xml(model):
    m = model

    def cylinder(link, index=0):
        visual = URDF.links[link].findall('visual')[index]
        g = visual.find('geometry/cylinder')
        return float(g.get('radius')), float(g.get('length')), visual

    radius, length, _ = cylinder('left_wheel')
    assert (radius, 0.5 * length) == pytest.approx(m.geom('left_wheel').size[:2])
    radius, length, _ = cylinder('tail', 1)
    assert (radius, 0.5 * length) == pytest.approx(m.geom('tail_wheel').size[:2])
    box = _floats(URDF.links['body'].find('visual/geometry/box').get('size'))
    assert 0.5 * box == pytest.approx(m.geom('body').size)
    # Links: robot.xml's capsules (fromto compiled to a centre and a half length).
    for link, body in (('left_front_thigh', 'left_front_thigh'),
                       ('left_rear_shank', 'left_rear_shank')):
        gid = next(g for g in range(m.ngeom) if m.geom_bodyid[g] == m.body(body).id)
        radius, length, visual = cylinder(link)
        assert (radius, 0.5 * length) == pytest.approx(m.geom_size[gid][:2])
        assert _floats(visual.find('origin').get('xyz')) == pytest.approx(m.geom_pos[gid])
    radius, length, visual = cylinder('tail', 0)
    strut = m.geom('tail_strut')
    assert (radius, 0.5 * length) == pytest.approx(strut.size[:2], abs=1e-8)
    centre = URDF.pose('tail', _joint_positions(0.5, 0.5))[:3, 3] + \
        _floats(visual.find('origin').get('xyz'))
    assert centre == pytest.approx(strut.pos, abs=1e-12)
    axis = Rotation.from_euler('xyz', _floats(visual.find('origin').get('rpy'))).apply([0, 0, 1])
    mj_axis = Rotation.from_quat(strut.quat[[1, 2, 3, 0]]).apply([0, 0, 1])
    assert abs(axis @ mj_axis) == pytest.approx(1.0, abs=1e-8)


@pytest.mark.parametrize('q_front,q_rear', HIP_GRID[::3])
def test_wheels_where_mujoco_puts_them_for_the_same_hip_angles(model, q_front, q_rear):
    data = mujoco.MjData(model)
    q = _joint_positions(q_front, q_rear)
    data.qpos[:] = model.qpos0  # base_link at the origin, unrotated
    data.qpos[0:3] = 0.0
    for name, value in q.items():
        data.qpos[model.jnt_qposadr[model.joint(name).id]] = value
    mujoco.mj_kinematics(model, data)
    for side in SIDES:
        wheel = URDF.pose(side + '_wheel', q)
        assert wheel[:3, 3] == pytest.approx(data.body(side + '_wheel').xpos, abs=1e-9)
        assert wheel[:3, :3] == pytest.approx(data.body(side + '_wheel').xmat.reshape(3, 3),
                                              abs=1e-9)
        # MuJoCo's closure constraint is satisfied by the knee angles too.
        assert data.site(side + '_rear_end').xpos == \
            pytest.approx(data.site(side + '_axle').xpos, abs=1e-9)


@pytest.mark.parametrize('l', [0.37, 0.55, 0.70])
@pytest.mark.parametrize('pitch', [-0.3, 0.0, 0.2, 0.6])
def test_footprint_to_base_link_is_where_mujoco_stands_the_robot(l, pitch):
    sim = RobotSim(height=l)
    sim.place(pitch)
    d = sim.data
    axle = 0.5 * (d.body('left_wheel').xpos + d.body('right_wheel').xpos)
    # place() sinks the wheels CONTACT_DEPTH into the soft floor: the axle is that much lower.
    t, q = base_footprint_to_base_link(pitch, *LEG.axle(*LEG.inverse(l)),
                                       WHEEL_RADIUS - CONTACT_DEPTH)
    footprint = np.array([axle[0], axle[1], 0.0])
    assert footprint + t == pytest.approx(d.body('base_link').xpos, abs=1e-9)
    assert Rotation.from_quat(q).as_matrix() == \
        pytest.approx(d.body('base_link').xmat.reshape(3, 3), abs=1e-12)


def test_urdf_is_installed():
    setup = (REPO / 'setup.py').read_text()
    assert "glob('urdf/*.urdf')" in setup
    assert math.isfinite(URDF.mass('left_wheel'))
