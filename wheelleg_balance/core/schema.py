"""
Typed configuration with its parameter schema stated once, on the dataclass fields.

A configuration is a tree of dataclasses. Each leaf field is declared with ``param(default,
description, lo, hi, read_only=...)``; a field that holds another configuration dataclass is
declared with ``section(Type, prefix)``. From that one statement this module derives what the
ROS side needs (nodes/params.py turns a ``ParamSpec`` into a declaration with its descriptor),
what a config file must look like, and the checks a value must pass, so a default, a range or a
description never exists in two places (the shape of generate_parameter_library's YAML schema
for ros2_controllers, in plain dataclasses).

Parameter names: a section's prefix joined with the field name by '.', e.g. ``can.mit.t_max``;
an empty prefix puts a section's fields at the top level (``fall_angle``); ``param(name=...)``
overrides the derived name for a field whose ROS name does not follow the rule.
No rclpy here.
"""
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass, field, fields, is_dataclass, replace
import functools
import math
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple

#: Types a parameter value may have (rclpy's parameter types).
SCALAR_TYPES = (bool, int, float, str)


class LiveChoices(SequenceABC):
    """
    The allowed values of a str parameter, read from ``source()`` whenever they are asked for.

    For choices from a table that grows at run time (core/protocols' ``register_protocol``):
    a check made after the registration admits the new name.
    """

    def __init__(self, source: Callable[[], Sequence[str]]):
        self._source = source

    def __getitem__(self, index):
        return tuple(self._source())[index]

    def __len__(self) -> int:
        return len(tuple(self._source()))

    def __contains__(self, value) -> bool:
        return value in tuple(self._source())

    def __repr__(self) -> str:
        return 'LiveChoices(%r)' % (tuple(self._source()),)


@dataclass(frozen=True)
class ParamSpec:
    """
    One parameter: where it lives in the configuration and what a valid value is.

    name: the ROS parameter name; path: attribute names from the root configuration to the
    field; default; kind: bool, int, float, str or list; item: the element type of a list;
    description (with the unit in brackets); lo/hi: inclusive range of a number (or of every
    element of a list); read_only: cannot change while the node runs; step: an integer range's
    step (2 with lo -1, hi 1 admits exactly -1 and +1); choices: the allowed values of a str
    (a LiveChoices: read at each check);
    length: the required length of a list (None: any). A default of None means unset: the
    value stays None unless given, and the node derives what it means.
    """

    name: str
    path: Tuple[str, ...]
    default: Any
    kind: type
    item: Optional[type]
    description: str
    lo: Optional[float] = None
    hi: Optional[float] = None
    read_only: bool = False
    step: int = 0
    choices: Sequence[str] = ()
    length: Optional[int] = None

    def check(self, value: Any) -> Optional[str]:
        """Return why ``value`` is not valid for this parameter, or None when it is."""
        if value is None and self.default is None:
            return None   # unset
        if self.kind is list:
            if not isinstance(value, (list, tuple)):
                return '%s must be a list, got %r' % (self.name, value)
            if self.length is not None and len(value) != self.length:
                return '%s needs %d entries, got %d' % (self.name, self.length, len(value))
            for v in value:
                problem = self._check_scalar(v, self.item)
                if problem:
                    return problem
            return None
        return self._check_scalar(value, self.kind)

    def _check_scalar(self, value: Any, kind: type) -> Optional[str]:
        if kind is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        elif kind is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        else:
            ok = isinstance(value, kind)
        if not ok:
            return '%s must be of type %s, got %r' % (self.name, kind.__name__, value)
        if kind is float and not math.isfinite(value):
            return '%s must be a finite number, got %r' % (self.name, value)
        if self.lo is not None and kind in (int, float) and not self.lo <= value <= self.hi:
            return '%s = %r is outside [%g, %g]' % (self.name, value, self.lo, self.hi)
        if self.step > 1 and kind is int and (value - int(self.lo)) % self.step:
            return '%s = %r is not one of %s' % (self.name, value, list(
                range(int(self.lo), int(self.hi) + 1, self.step)))
        if self.choices and value not in self.choices:
            return 'unknown %s %r: one of %s' % (self.name, value, ', '.join(self.choices))
        return None


def param(default: Any, description: str, lo: Optional[float] = None,
          hi: Optional[float] = None, *, read_only: bool = False, step: int = 0,
          choices: Sequence[str] = (), length: Optional[int] = None, item: Optional[type] = None,
          name: Optional[str] = None, kind: Optional[type] = None):
    """
    Declare a leaf field: its default, description (unit in brackets), range and access.

    A list default gets a fresh copy per instance; ``item`` gives a list's element type when the
    default is empty. A default of None is unset (the node derives the value; say how in the
    description) and needs ``kind``, the type of a value when one is given. ``name`` overrides
    the derived ROS parameter name.
    """
    md = {'param': {'description': description, 'lo': lo, 'hi': hi, 'read_only': read_only,
                    'step': step, 'length': length, 'item': item,
                    'name': name, 'kind': kind,
                    'choices': choices if isinstance(choices, LiveChoices) else tuple(choices)}}
    if isinstance(default, (list, tuple)):
        value = tuple(default)
        return field(default_factory=lambda: list(value), metadata=md)
    return field(default=default, metadata=md)


def section(cls: type, prefix: str = ''):
    """Declare a field that holds the configuration dataclass ``cls`` under ``prefix``."""
    return field(default_factory=cls, metadata={'section': prefix})


def _join(prefix: str, name: str) -> str:
    return '%s.%s' % (prefix, name) if prefix else name


@functools.lru_cache(maxsize=None)
def specs(cls: type) -> Tuple[ParamSpec, ...]:
    """Return every parameter of configuration class ``cls``, in declaration order."""
    out: List[ParamSpec] = []
    _collect(cls, '', (), out)
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise TypeError('%s declares these parameter names twice: %s'
                        % (cls.__name__, ', '.join(dup)))
    return tuple(out)


def _collect(cls: type, prefix: str, path: Tuple[str, ...], out: List[ParamSpec]) -> None:
    defaults = cls()
    for f in fields(cls):
        if 'section' in f.metadata:
            _collect(f.default_factory, _join(prefix, f.metadata['section']), path + (f.name,),
                     out)
            continue
        md = f.metadata.get('param')
        if md is None:
            continue  # a private field without a parameter
        default = getattr(defaults, f.name)
        if isinstance(default, list):
            kind = list
            item = md['item'] or (type(default[0]) if default else None)
            if item is None:
                raise TypeError('%s.%s: an empty list default needs item='
                                % (cls.__name__, f.name))
        else:
            kind, item = (md['kind'] if default is None else type(default)), None
            if kind not in SCALAR_TYPES:
                raise TypeError('%s.%s: unsupported parameter type %s (a None default needs '
                                'kind=)' % (cls.__name__, f.name, getattr(kind, '__name__', kind)))
        out.append(ParamSpec(
            name=md['name'] or _join(prefix, f.name), path=path + (f.name,), default=default,
            kind=kind, item=item, description=md['description'], lo=md['lo'], hi=md['hi'],
            read_only=md['read_only'], step=md['step'], choices=md['choices'],
            length=md['length']))


def spec_by_name(cls: type) -> Dict[str, ParamSpec]:
    """Return {parameter name: ParamSpec} of configuration class ``cls``."""
    return {s.name: s for s in specs(cls)}


def _get(cfg: Any, path: Tuple[str, ...]) -> Any:
    for attr in path:
        cfg = getattr(cfg, attr)
    return cfg


def to_flat(cfg: Any) -> Dict[str, Any]:
    """Return {parameter name: value} of a configuration (lists copied)."""
    out = {}
    for s in specs(type(cfg)):
        v = _get(cfg, s.path)
        out[s.name] = list(v) if isinstance(v, (list, tuple)) else v
    return out


def _coerce(s: ParamSpec, value: Any) -> Any:
    # Integers are valid doubles (a YAML file may write 1 for 1.0); store them as floats.
    if s.kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if s.kind is list:
        value = list(value) if isinstance(value, (list, tuple)) else value
        if s.item is float and isinstance(value, list):
            return [float(v) if isinstance(v, int) and not isinstance(v, bool) else v
                    for v in value]
    return value


def with_changes(cfg: Any, changes: Mapping[str, Any]) -> Any:
    """
    Return a copy of ``cfg`` with {parameter name: value} applied (cfg is not modified).

    Raises ValueError for an unknown name or a value that fails its ParamSpec check.
    """
    by_name = spec_by_name(type(cfg))
    grouped: Dict[Tuple[str, ...], Dict[str, Any]] = {}
    for name, value in changes.items():
        s = by_name.get(name)
        if s is None:
            raise ValueError('unknown parameter %r' % name)
        value = _coerce(s, value)
        problem = s.check(value)
        if problem:
            raise ValueError(problem)
        grouped.setdefault(s.path[:-1], {})[s.path[-1]] = value
    return _replace_tree(cfg, (), grouped)


def _replace_tree(obj: Any, path: Tuple[str, ...], grouped) -> Any:
    updates = dict(grouped.get(path, {}))
    for f in fields(obj):
        if 'section' in f.metadata:
            sub_path = path + (f.name,)
            if any(p[:len(sub_path)] == sub_path for p in grouped):
                updates[f.name] = _replace_tree(getattr(obj, f.name), sub_path, grouped)
    return replace(obj, **updates) if updates else obj


def from_flat(cls: type, values: Mapping[str, Any]) -> Any:
    """Build a configuration of class ``cls`` from {parameter name: value}; others default."""
    return with_changes(cls(), values)


def check(cfg: Any) -> List[str]:
    """
    Return every problem of a configuration: per-parameter checks, then the cross-field rules.

    A section may define ``problems(self) -> List[str]`` for rules between its fields; the root
    configuration's ``problems`` sees the whole tree.
    """
    out = [p for p in (s.check(_get(cfg, s.path)) for s in specs(type(cfg))) if p]
    if out:
        return out
    return _section_problems(cfg)


def _section_problems(obj: Any) -> List[str]:
    out: List[str] = []
    for f in fields(obj):
        if 'section' in f.metadata:
            out += _section_problems(getattr(obj, f.name))
    rules = getattr(obj, 'problems', None)
    if rules is not None:
        out += rules()
    return out


def flatten_yaml(tree: Mapping[str, Any], prefix: str = '') -> Dict[str, Any]:
    """Turn a nested ``ros__parameters`` mapping into {dotted name: value}, as rclpy does."""
    out: Dict[str, Any] = {}
    for key, value in tree.items():
        name = _join(prefix, str(key))
        if isinstance(value, Mapping):
            out.update(flatten_yaml(value, name))
        else:
            out[name] = value
    return out


def nest(flat: Mapping[str, Any]) -> Dict[str, Any]:
    """Inverse of flatten_yaml: {'can.mit.t_max': 18.0} -> {'can': {'mit': {'t_max': 18.0}}}."""
    out: Dict[str, Any] = {}
    for name, value in flat.items():
        node = out
        *parents, leaf = name.split('.')
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def is_config(obj: Any) -> bool:
    """Return True when ``obj`` is a configuration dataclass instance."""
    return is_dataclass(obj) and not isinstance(obj, type)
