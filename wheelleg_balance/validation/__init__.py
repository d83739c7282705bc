"""
Validation of the product, apart from it: the paper's experiments, faults, benchmarks.

``paper``: the paper's experiments on model (1) (``experiments``) and through the real processes
against the MuJoCo robot (``main_job``), from one table of experiments, metrics and criteria.
"""
import math
import os
import pathlib
from typing import Any, Dict, Optional

import numpy as np


def package_parent() -> str:
    """Return the directory that holds the wheelleg_balance package (source or install)."""
    return str(pathlib.Path(__file__).resolve().parents[2])


def child_env(env: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """Return an environment in which child processes import this very package first."""
    env = dict(os.environ if env is None else env)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (package_parent(), env.get('PYTHONPATH'))
                                        if p)
    return env


def json_safe(value: Any) -> Any:
    """Return a JSON-safe copy: NaN and infinities become None, numpy scalars plain numbers."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
