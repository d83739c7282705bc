"""
The default configuration's height tables, solved at build time (core/table_cache.py).

setup.py runs ``write_defaults`` into the installed package, so balance_node with the default
model starts without solving them. Building a BalanceLoop of the default configuration solves
every table its controllers and observer need; the planned rise's (core/rise.py) is solved too,
although ``auto.planned_rise`` is off by default, so that turning it on costs no solve at start.
"""
from dataclasses import replace
import os

from . import table_cache
from .balance_loop import BalanceLoop
from .config import BalanceConfig


def write_defaults(folder: str) -> int:
    """Solve the default configuration's tables into ``folder``; return how many there are."""
    with table_cache.solving_into(folder):
        cfg = BalanceConfig()
        BalanceLoop(replace(cfg, auto=replace(cfg.auto, planned_rise=True)))
    return sum(1 for n in os.listdir(folder) if n.endswith('.json'))
