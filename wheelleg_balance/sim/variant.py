"""
A robot that is not the default: sim_node's ``robot.*`` quantities applied to robot.xml.

``apply_body`` changes an mjSpec of robot.xml (MuJoCo's model-editing API, not the XML text)
where a quantity of sim/config.RobotBodyConfig differs from its default, so the defaults
compile to exactly today's model. ``CommandDelay`` holds the motors' commands back by
``robot.motor_delay`` (a latency between a command and the torque it asks for), linearly
interpolated between physics steps, so a delay need not be a whole number of steps.
"""
from collections import deque
from typing import List, Sequence

from .config import RobotBodyConfig

#: The defaults, to leave what was not asked for as robot.xml has it.
DEFAULT_BODY = RobotBodyConfig()
#: The wheels' bodies, geoms and joints in robot.xml.
_WHEELS = ('left_wheel', 'right_wheel')


def _changed(body: RobotBodyConfig, name: str) -> bool:
    return getattr(body, name) != getattr(DEFAULT_BODY, name)


def apply_body(spec, body: RobotBodyConfig) -> None:
    """Set the body's and the wheels' mass properties, radius and damping in an mjSpec."""
    base = spec.body('base_link')
    if _changed(body, 'body_mass'):
        base.mass = body.body_mass
    if _changed(body, 'body_com'):
        base.ipos = [body.body_com[0], 0.0, body.body_com[1]]
    if _changed(body, 'body_inertia'):
        ixx, _, izz = base.inertia
        base.inertia = [ixx, body.body_inertia, izz]   # principal axes = base_link's
    radius = body.wheel_radius
    for name in _WHEELS:
        geom = spec.geom(name)
        if _changed(body, 'wheel_radius'):
            geom.size = [radius, geom.size[1], geom.size[2]]
        if _changed(body, 'wheel_mass'):
            geom.mass = body.wheel_mass
        if _changed(body, 'wheel_inertia'):
            # An explicit inertial: the axle (y) inertia as asked; about the other axes the
            # disc's, raised where needed to keep the triangle inequality MuJoCo checks.
            wheel = spec.body(name)
            half_width = geom.size[1]
            m = body.wheel_mass
            radial = max(m * (3.0 * radius ** 2 + (2.0 * half_width) ** 2) / 12.0,
                         0.5 * body.wheel_inertia)
            wheel.explicitinertial = True
            wheel.mass = m
            wheel.ipos = [0.0, 0.0, 0.0]
            wheel.iquat = [1.0, 0.0, 0.0, 0.0]
            wheel.inertia = [radial, body.wheel_inertia, radial]
        if _changed(body, 'wheel_damping'):
            joint = spec.joint(name + '_joint')
            damping = list(joint.damping)
            damping[0] = body.wheel_damping   # the linear (viscous) coefficient
            joint.damping = damping


class CommandDelay:
    """
    The motors' commands held back by ``delay`` [s] at physics steps of ``timestep`` [s].

    ``push(values)`` takes the commands of one physics step and returns those that act now:
    the ones of ``delay`` ago, interpolated between the two steps around it (zeros before
    the first command).
    """

    def __init__(self, delay: float, timestep: float, size: int):
        steps = delay / timestep
        self._whole = int(steps)
        self._frac = steps - self._whole
        self._size = size
        self._history: deque = deque(maxlen=self._whole + 2)
        self.clear()

    def clear(self) -> None:
        """Forget the commands (a reset: nothing commanded yet)."""
        self._history.clear()
        for _ in range(self._history.maxlen):
            self._history.append([0.0] * self._size)

    def push(self, values: Sequence[float]) -> List[float]:
        """Take one step's commands; return the ones acting now (see the class docstring)."""
        self._history.append(list(values))
        h = self._history
        now = h[-1 - self._whole]
        before = h[-2 - self._whole]
        f = self._frac
        return [(1.0 - f) * a + f * b for a, b in zip(now, before)]
