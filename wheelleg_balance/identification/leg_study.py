"""
A study: is the body inertia's bias the legs' give? The balance phase with stiffer legs.

The fitted body inertia I_b comes out about 10 % low (docs/identification.md). The suspect
was the legs: the five-bar's closure is a soft constraint in MuJoCo (``connect``, solref 0.004
s) and the hips are position servos (kp 3000 N m/rad), so the body might move on its legs
while it balances, which the fit's rigid pendulum does not model. ``run`` plays the balance
phase of a variant with the closure's time constant and the hip servos' gains changed
(``stiff_legs``, which edits the mjSpec after sim/variant.py ``apply_body``), fits it with the
stand's and tail's quantities at the simulator's values (so only the balance fit is judged),
and reports I_b's error, the hips' RMS motion about each run's mean and the fit's residual.
``python -m wheelleg_balance.identification.leg_study [VARIANT]`` prints the table.
"""
from contextlib import contextmanager
import sys
import time
from typing import Dict, List, Optional

import numpy as np

from . import excite, fit, study
from .records import JOINTS
from ..core.kinematics import FiveBarLeg
from ..core.schema import from_flat
from ..sim import robot_sim
from ..sim.config import RobotBodyConfig
from ..sim.layout import LEG_JOINTS

#: The cases: closure time constant [s] (robot.xml 0.004; twice the 0.5 ms step is the least
#: MuJoCo keeps stable), hip servo kp [N m/rad] and kv [N m s/rad] (robot.xml 3000, 60).
CASES = ({'label': "robot.xml's legs"},
         {'label': 'closure 4x stiffer', 'closure': 0.001},
         {'label': 'closure 4x, hip servos 10x stiffer', 'closure': 0.001, 'kp': 30000.0,
          'kv': 300.0})


@contextmanager
def stiff_legs(closure: Optional[float] = None, kp: Optional[float] = None,
               kv: Optional[float] = None):
    """Within the block, RobotSim's legs have these closure and hip servo constants."""
    original = robot_sim.apply_body

    def apply(spec, body):
        original(spec, body)
        if closure is not None:
            for name in ('left_closure', 'right_closure'):
                spec.equality(name).solref = [closure, 1.0]
        if kp is not None:
            for act in spec.actuators:
                if act.name.endswith('_servo'):   # position servo: gain kp, bias -kp q - kv q_dot
                    act.gainprm[0] = kp
                    act.biasprm[1] = -kp
                    act.biasprm[2] = -kv
    robot_sim.apply_body = apply
    try:
        yield
    finally:
        robot_sim.apply_body = original


def hip_motion(rec) -> float:
    """Return the hips' RMS angle about each run's mean [rad] (the runs split at the gaps)."""
    js = rec[JOINTS]
    q = np.array([js[n + '.position'] for n in LEG_JOINTS])
    edges = np.concatenate([[0], np.flatnonzero(np.diff(js.t) > 0.5 * excite.GAP) + 1,
                            [len(js.t)]])
    dev = [q[:, a:b] - q[:, a:b].mean(axis=1, keepdims=True) for a, b in zip(edges, edges[1:])]
    return float(np.sqrt(np.mean(np.concatenate([d.ravel() for d in dev]) ** 2)))


def run(name: str) -> List[Dict]:
    """Return one row per CASES entry for variant ``name`` (module docstring)."""
    body = from_flat(RobotBodyConfig, study.VARIANTS[name])
    est = fit.Estimate
    stand = {'robot.wheel_inertia': est(body.wheel_inertia, 0.0, 'kg m^2'),
             'robot.wheel_damping': est(body.wheel_damping, 0.0, 'N m s/rad'),
             'robot.motor_delay': est(body.motor_delay, 0.0, 's')}
    tail = {'robot.wheel_radius': est(body.wheel_radius, 0.0, 'm')}
    rows = []
    for case in CASES:
        start = time.monotonic()
        with stiff_legs(case.get('closure'), case.get('kp'), case.get('kv')):
            rec = excite.play_balance(body, study.D_OFFSET)
        got = fit.fit_balance(rec, stand, tail, FiveBarLeg())
        i_b = got['robot.body_inertia'].value
        rows.append({'variant': name, 'case': case['label'], 'body_inertia': i_b,
                     'error_pct': 100.0 * (i_b / body.body_inertia - 1.0),
                     'body_mass_error_pct': 100.0 * (got['robot.body_mass'].value
                                                     / body.body_mass - 1.0),
                     'hip_rms_mrad': 1e3 * hip_motion(rec),
                     'residual_nm': got['_residual_rms'].value,
                     'seconds': time.monotonic() - start})
    return rows


def main(argv=None) -> None:
    """Print the table of docs/identification.md for the variants named (default: two)."""
    names = (argv if argv is not None else sys.argv[1:]) or ['light_low_small',
                                                             'heavy_high_large']
    print('| variant | legs | I_b fitted [kg m^2] | I_b error | body mass error | hips RMS '
          '[mrad] | residual RMS [N m] |')
    print('|---|---|---|---|---|---|---|')
    for name in names:
        for r in run(name):
            print('| %s | %s | %.4f | %+.1f %% | %+.2f %% | %.3f | %.4f |' % (
                r['variant'], r['case'], r['body_inertia'], r['error_pct'],
                r['body_mass_error_pct'], r['hip_rms_mrad'], r['residual_nm']))


if __name__ == '__main__':
    main()
