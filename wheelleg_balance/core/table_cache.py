"""
Height-grid tables solved once per set of inputs: the LQR schedule and the observer's matrices.

BalanceCore's constructor solves a Riccati equation (core/lqr.py ``GainSchedule``) and places
the observer's poles (core/observer.py ``DisturbanceObserver``) at each of the 34 grid heights:
1.4 s of balance_node's start on this project's 2-core VM at load 1, far more on a Raspberry Pi
(docs/benchmarks.md, "Start-up"). The tables depend on their inputs alone, so ``table`` solves
them once and afterwards looks them up:

1. in this process's memory (the fault suite, the experiments and the tuning build many cores);
2. among the package's tables (``tables/`` beside this module): the build solves those of the
   default configuration into the installed package (setup.py runs core/default_tables.py);
3. in a cache folder, where a process that asked for it (``keep_in``: balance_node's control
   process) writes what it had to solve, such as the tables of a robot's own model parameters.

A table is found by its key: its name, every input (floats as their exact repr), the versions
of numpy and scipy and the machine's architecture, since the values are those these libraries
compute here, bit for bit (test/test_table_cache.py checks a looked-up table against a fresh
solve). The files are JSON (a float's shortest repr reads back as the same float), written to a
temporary name and renamed into place; a file whose key or shape does not match is ignored.
No scipy solver is imported here (its top level only, for the version): solving is the
caller's, and a table found is not solved.
"""
from contextlib import contextmanager
import dataclasses
import hashlib
import json
import os
import platform
import tempfile
from typing import Callable, Dict, Iterator, Optional, Tuple

import numpy as np

#: The package's own tables (the default configuration's, solved by the build).
PACKAGE_TABLES = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'tables')
#: The cache folder's environment variable (balance_node's control process; empty: none).
CACHE_ENV = 'WHEELLEG_BALANCE_CACHE'
#: At most this many tables stay in a cache folder (the oldest go first).
MAX_FILES = 64

_memory: Dict[str, Tuple[str, np.ndarray]] = {}
_package: Optional[str] = PACKAGE_TABLES
_folder: Optional[str] = None


def floats(value):
    """Return ``value`` (a dataclass of floats, an array, a number, nested lists) as floats."""
    if dataclasses.is_dataclass(value):
        return {f.name: floats(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [floats(v) for v in value]
    return float(value)


def key(name: str, inputs: dict) -> dict:
    """Return the key of table ``name`` solved from ``inputs`` on this machine's libraries."""
    import scipy   # its version only (the package's top level, not its solvers)
    return {'table': name, 'inputs': inputs, 'numpy': np.__version__,
            'scipy': scipy.__version__, 'machine': platform.machine()}


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def table(name: str, inputs: dict, solve: Callable[[], np.ndarray]) -> np.ndarray:
    """
    Return the table ``solve()`` gives for ``inputs`` (a copy: the caller's own).

    name: what it is ('lqr_gains', 'observer_rows'); inputs: everything ``solve`` reads, as
    JSON-able floats (``floats``).
    """
    text = json.dumps(key(name, inputs), sort_keys=True)
    digest = _digest(text)
    hit = _memory.get(digest)
    if hit is None or hit[0] != text:
        values = None if _package is None else _read(_package, digest, text)
        if values is None and _folder is not None:
            values = _read(_folder, digest, text)
        if values is None:
            values = np.array(solve(), dtype=float)
            if _folder is not None and np.all(np.isfinite(values)):
                _write(_folder, digest, text, values)
        hit = _memory[digest] = (text, values)
    return hit[1].copy()


def _read(folder: str, digest: str, text: str) -> Optional[np.ndarray]:
    """Return the table of file ``digest`` in ``folder`` if its key is ``text``, else None."""
    try:
        with open(os.path.join(folder, digest + '.json')) as f:
            data = json.load(f)
        if json.dumps(data['key'], sort_keys=True) != text:
            return None
        values = np.array(data['values'], dtype=float)
        if list(values.shape) != data['shape'] or not np.all(np.isfinite(values)):
            return None
        return values
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _write(folder: str, digest: str, text: str, values: np.ndarray) -> None:
    """Write a table atomically; a folder that cannot take it is left alone (the next solves)."""
    try:
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix='.' + digest, suffix='.tmp', dir=folder)
        try:
            with os.fdopen(fd, 'w') as f:
                json.dump({'key': json.loads(text), 'shape': list(values.shape),
                           'values': values.tolist()}, f, allow_nan=False)
            os.chmod(tmp, 0o644)   # mkstemp's 0600 would hide an installed table from users
            os.replace(tmp, os.path.join(folder, digest + '.json'))
        except BaseException:
            os.unlink(tmp)
            raise
        _prune(folder)
    except (OSError, ValueError):
        pass


def _prune(folder: str) -> None:
    """Keep the newest MAX_FILES tables of a cache folder."""
    paths = [os.path.join(folder, n) for n in os.listdir(folder) if n.endswith('.json')]
    if len(paths) > MAX_FILES:
        paths.sort(key=os.path.getmtime)
        for path in paths[:len(paths) - MAX_FILES]:
            os.unlink(path)


def default_folder() -> Optional[str]:
    """Return the cache folder: $WHEELLEG_BALANCE_CACHE (empty: none), else the user's cache."""
    folder = os.environ.get(CACHE_ENV)
    if folder is not None:
        return folder or None
    base = os.environ.get('XDG_CACHE_HOME') or os.path.join(os.path.expanduser('~'), '.cache')
    return os.path.join(base, 'wheelleg_balance')


def keep_in(folder: Optional[str]) -> None:
    """Look tables up in ``folder`` and write the ones solved there (None: no folder)."""
    global _folder
    _folder = folder


def forget() -> None:
    """Empty this process's memory of tables (tests)."""
    _memory.clear()


@contextmanager
def solving_into(folder: str) -> Iterator[None]:
    """
    Within the block, solve every table anew and write it into ``folder`` (the build's).

    The folder's older tables go first: it holds exactly what was solved within the block
    (core/default_tables.py solves the default configuration's).
    """
    global _package
    os.makedirs(folder, exist_ok=True)
    for name in os.listdir(folder):
        if name.endswith('.json'):
            os.unlink(os.path.join(folder, name))
    previous = _package, _folder
    _package = None   # solve every table, whatever the package already holds
    keep_in(folder)
    forget()
    try:
        yield
    finally:
        _package, _ = previous
        keep_in(previous[1])
