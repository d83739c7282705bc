"""
Validation of the product, apart from it: the paper's experiments, faults, benchmarks.

``paper``: the paper's experiments on model (1) (``experiments``) and through the real processes
against the MuJoCo robot (``main_job``), from one table of experiments, metrics and criteria.
"""
import os
import pathlib
from typing import Dict, Optional


def package_parent() -> str:
    """Return the directory that holds the wheelleg_balance package (source or install)."""
    return str(pathlib.Path(__file__).resolve().parents[2])


def child_env(env: Optional[Dict[str, str]] = None) -> Dict[str, str]:
    """Return an environment in which child processes import this very package first."""
    env = dict(os.environ if env is None else env)
    env['PYTHONPATH'] = os.pathsep.join(p for p in (package_parent(), env.get('PYTHONPATH'))
                                        if p)
    return env
