"""
The generated tables of the docs: parameters (docs/interface.md) and safety reactions.

Every parameter's name, type, default, range, read-only flag and description is stated once, on
its configuration dataclass (core/config.py, sim/config.py, the teleop node's); this module
renders them as markdown between the markers ``<!-- parameters:NODE -->`` and ``<!-- /parameters
-->`` in docs/interface.md. Every fault and warning code's detection, reaction and recovery is
stated once, in core/safety.py's SAFETY_TABLE; it is rendered between ``<!-- safety_table -->``
and ``<!-- /safety_table -->`` in docs/balance_node.md. So the documentation cannot drift from
the code (test/test_interface_doc.py checks both are current).

    python -m wheelleg_balance.validation.interface_doc          # check: exit 1 when stale
    python -m wheelleg_balance.validation.interface_doc --write  # rewrite the tables
"""
import argparse
import math
import pathlib
import re
import sys
from typing import Dict, List

from ..core.config import BalanceConfig
from ..core.safety import OTHER_REACTIONS, SAFETY_TABLE
from ..core.schema import specs
from ..sim.config import SimConfig

DOCS = pathlib.Path(__file__).resolve().parents[2] / 'docs'
#: The page of the parameter tables, next to the sources.
PAGE = DOCS / 'interface.md'
#: The page of the safety table.
SAFETY_PAGE = DOCS / 'balance_node.md'
MARKER = re.compile(r'(<!-- parameters:(?P<node>[a-z_]+) -->\n)(?P<body>.*?)'
                    r'(<!-- /parameters -->)', re.S)
SAFETY_MARKER = re.compile(r'(<!-- safety_table -->\n)(.*?)(<!-- /safety_table -->)', re.S)


def node_configs() -> Dict[str, type]:
    """Return {node name: its configuration class}."""
    from ..nodes.teleop_node import TeleopNodeConfig   # imports rclpy: only when asked
    return {'balance_node': BalanceConfig, 'sim_node': SimConfig,
            'teleop_node': TeleopNodeConfig}


def _value(v) -> str:
    if isinstance(v, float):
        if math.isinf(v):
            return 'inf' if v > 0 else '-inf'
        return '%.6g' % v
    if isinstance(v, (list, tuple)):
        return '[' + ', '.join(_value(x) for x in v) + ']'
    if v is None:
        return 'unset'
    if isinstance(v, str):
        return "'%s'" % v
    return str(v)


def _range(s) -> str:
    if s.choices:
        return ' \\| '.join(s.choices)
    if s.lo is None and s.hi is None:
        return ''
    return '%s .. %s' % (_value(s.lo) if s.lo is not None else '',
                         _value(s.hi) if s.hi is not None else '')


def parameter_table(cls: type) -> str:
    """Return the markdown table of every parameter of configuration ``cls``."""
    rows: List[str] = ['| name | type | default | range | live | description |',
                       '|---|---|---|---|---|---|']
    for s in specs(cls):
        kind = s.kind.__name__ if s.kind is not list else \
            'list of %s' % (s.item.__name__ if s.item else 'any')
        if s.length:
            kind += ' (%d)' % s.length
        desc = s.description.replace('|', '\\|').replace('\n', ' ')
        rows.append('| `%s` | %s | %s | %s | %s | %s |' % (
            s.name, kind, _value(s.default).replace('|', '\\|'), _range(s),
            'no' if s.read_only else 'yes', desc))
    return '\n'.join(rows) + '\n'


def safety_table() -> str:
    """Return the markdown table of every code of core/safety.py, then the other reactions."""
    rows = ['| code | detected when | reaction | recovery |', '|---|---|---|---|']
    for names, table in ((lambda c: '`%s`' % c, SAFETY_TABLE),
                         (lambda c: '(%s)' % c, OTHER_REACTIONS)):
        for code, r in table.items():
            rows.append('| %s | %s | %s | %s |' % (
                names(code), *(t.replace('|', '\\|') for t in r)))
    return '\n'.join(rows) + '\n'


def render_safety(text: str) -> str:
    """Return ``text`` with the marked safety table replaced by the current one."""
    if not SAFETY_MARKER.search(text):
        raise KeyError('no <!-- safety_table --> marker')
    return SAFETY_MARKER.sub(lambda m: m.group(1) + safety_table() + m.group(3), text)


def render(text: str) -> str:
    """Return ``text`` with every marked parameter table replaced by the current one."""
    configs = node_configs()

    def table(m: 're.Match') -> str:
        node = m.group('node')
        if node not in configs:
            raise KeyError('docs/interface.md names an unknown node %r' % node)
        return m.group(1) + parameter_table(configs[node]) + m.group(4)
    return MARKER.sub(table, text)


def main(argv=None) -> int:
    """Check (or with --write, rewrite) the generated tables of the docs."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--write', action='store_true', help='rewrite the tables in place')
    args = ap.parse_args(argv)
    stale = []
    for page, renderer in ((PAGE, render), (SAFETY_PAGE, render_safety)):
        old = page.read_text()
        new = renderer(old)
        if args.write:
            page.write_text(new)
        elif new != old:
            stale.append(str(page))
    if stale:
        print('%s: generated tables are stale; run python -m '
              'wheelleg_balance.validation.interface_doc --write' % ', '.join(stale),
              file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
