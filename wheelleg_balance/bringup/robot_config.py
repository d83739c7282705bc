"""
The robot's balance_node config file: read the one bring-up starts from, write the filled one.

A params file is ``{node name: {ros__parameters: {...}}}`` (nested or dotted keys, as rclpy
reads them). ``read_params`` takes balance_node's section (or ``/**``), ``filled_config``
applies the bring-up's changes and checks the whole configuration against core/config.py
(schema and cross-parameter rules), and ``write_params`` writes every parameter, nested, with
a header that says what was checked. No rclpy.
"""
import pathlib
from typing import Dict, List, Mapping, Sequence, Tuple

import yaml

from .motor_checks import apply_changes
from ..core.config import BalanceConfig
from ..core.schema import check, flatten_yaml, from_flat, nest, to_flat

NODE = 'balance_node'


def read_params(path: pathlib.Path, node: str = NODE) -> Dict[str, object]:
    """Return {dotted name: value} of node's section of a params file (ValueError if none)."""
    doc = yaml.safe_load(pathlib.Path(path).read_text()) or {}
    for key in (node, '/' + node, '/**'):
        body = doc.get(key)
        if isinstance(body, Mapping) and isinstance(body.get('ros__parameters'), Mapping):
            return flatten_yaml(body['ros__parameters'])
    raise ValueError('%s has no %s: ros__parameters section' % (path, node))


def build(flat: Mapping[str, object]) -> BalanceConfig:
    """Build and check a BalanceConfig from flat parameters (ValueError with every problem)."""
    cfg = from_flat(BalanceConfig, flat)
    problems = check(cfg)
    if problems:
        raise ValueError('; '.join(problems))
    return cfg


def filled_config(base: BalanceConfig, changes: Mapping[str, object]
                  ) -> Tuple[BalanceConfig, Dict[str, object]]:
    """Return the configuration with the bring-up's changes and its flat parameters."""
    flat = apply_changes(to_flat(base), dict(changes))
    return build(flat), flat


def write_params(path: pathlib.Path, cfg: BalanceConfig, header: Sequence[str],
                 node: str = NODE) -> pathlib.Path:
    """Write every parameter of cfg as node's params file, header lines as comments first."""
    path = pathlib.Path(path)
    body = yaml.safe_dump({node: {'ros__parameters': nest(to_flat(cfg))}}, sort_keys=False,
                          default_flow_style=None, width=99)
    lines: List[str] = ['# %s' % h if h else '#' for h in header]
    path.write_text('\n'.join(lines) + '\n' + body)
    return path
