"""
CAN motor protocols as pure byte codecs (no python-can): see docs/can_protocols.md.

``PROTOCOLS`` is the one table from a ``can.protocol`` / ``legs.can.protocol`` name to its
codec class; everything about a protocol is on that class and in its module (frames out,
replies in, special frames, its configuration section ``config``, frames per tick, reply
health, the position's wrap or saturation, its emulator). ``make_protocol(name, **params)``
builds a codec from keyword arguments, ``protocol_for(name, owner)`` from its configuration
section of ``can`` or ``legs``; ``register_protocol`` adds one (a test's, a builder's) at run
time, ``import_protocol('module:Class')`` in another process.
"""
import importlib
from typing import Any, Iterable, List, Optional, Tuple, Type

from .base import Frame, MotorFeedback, MotorProtocol
from .cybergear import CybergearConfig, CybergearProtocol
from .damiao import DamiaoConfig, DamiaoProtocol
from .dji import DjiC620Protocol
from .lk import LkConfig, LkProtocol
from .mit import MitCommand, MitProtocol

#: Protocol classes by ``can.protocol`` name.
PROTOCOLS = {cls.name: cls for cls in (MitProtocol, DjiC620Protocol, LkProtocol,
                                       CybergearProtocol, DamiaoProtocol)}


def protocol_class(name: str) -> Type[MotorProtocol]:
    """Return the codec class registered as ``name`` (ValueError naming the known ones)."""
    try:
        return PROTOCOLS[name]
    except KeyError:
        raise ValueError('unknown CAN protocol %r (one of %s)'
                         % (name, ', '.join(sorted(PROTOCOLS)))) from None


def make_protocol(name: str, **params) -> MotorProtocol:
    """Build protocol ``name`` ('mit', 'dji_c620', 'lk', ...) with its constructor parameters."""
    return protocol_class(name)(**params)


def protocol_for(name: str, owner: Any) -> MotorProtocol:
    """
    Build protocol ``name`` from its section of ``owner`` (a CanConfig or LegsConfig).

    The section is the class's ``config_section`` attribute of owner; a protocol whose section
    owner lacks (one defined outside the package) gets its defaults.
    """
    cls = protocol_class(name)
    return cls.from_config(getattr(owner, cls.config_section, None) if cls.config_section
                           else None)


def check_motors(name: str, owner: Any,
                 motor_ids: Iterable[int]) -> Tuple[Optional[MotorProtocol], List[str]]:
    """
    Build protocol ``name`` from its section of ``owner`` and judge ``motor_ids`` with it.

    Return (the codec, its id_problems), or (None, why the codec refused the figures).
    """
    try:
        protocol = protocol_for(name, owner)
    except ValueError as e:
        return None, ['%s motor figures: %s' % (name, e)]
    return protocol, protocol.id_problems(motor_ids)


def impedance_protocols():
    """Return the names of the protocols that send impedance commands (command_frame): hips."""
    return tuple(n for n, cls in PROTOCOLS.items()
                 if callable(getattr(cls, 'command_frame', None)))


def import_protocol(spec: str) -> Type[MotorProtocol]:
    """
    Import and register the protocol ``spec`` names: 'package.module:ClassName'.

    How another process (sim_node, bring-up's) gets a protocol defined outside the package: its
    module must be importable there (on its sys.path). ValueError for a bad spec.
    """
    module, sep, name = spec.partition(':')
    if not (sep and module and name):
        raise ValueError('a protocol is named module:Class, got %r' % spec)
    try:
        cls = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError('cannot load protocol %s: %s' % (spec, e)) from None
    return register_protocol(cls)


def register_protocol(cls: Type[MotorProtocol]) -> Type[MotorProtocol]:
    """Add a MotorProtocol subclass to the table under its ``name`` (usable as a decorator)."""
    if not (isinstance(cls, type) and issubclass(cls, MotorProtocol) and cls.name):
        raise ValueError('a protocol is a MotorProtocol subclass with a name')
    PROTOCOLS[cls.name] = cls
    return cls


__all__ = ['check_motors', 'CybergearConfig', 'CybergearProtocol', 'DamiaoConfig',
           'DamiaoProtocol', 'DjiC620Protocol', 'Frame', 'impedance_protocols', 'import_protocol',
           'LkConfig', 'LkProtocol', 'make_protocol', 'MitCommand', 'MitProtocol', 'MotorFeedback',
           'MotorProtocol', 'protocol_class', 'protocol_for', 'PROTOCOLS', 'register_protocol']
