"""
The default configuration's height tables, solved at build time (core/table_cache.py).

setup.py runs ``write_defaults`` into the installed package, so balance_node with the default
model starts without solving them. Building a BalanceLoop of the default configuration solves
every table its controllers and observer need.
"""
import os

from . import table_cache
from .balance_loop import BalanceLoop
from .config import BalanceConfig


def write_defaults(folder: str) -> int:
    """Solve the default configuration's tables into ``folder``; return how many there are."""
    with table_cache.solving_into(folder):
        BalanceLoop(BalanceConfig())
    return sum(1 for n in os.listdir(folder) if n.endswith('.json'))
