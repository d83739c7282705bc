"""
CAN motor protocols as pure byte codecs (no python-can): see docs/can_protocols.md.

``make_protocol(name, **params)`` builds the codec the node's ``can.protocol`` parameter names.
"""
from .base import Frame, MotorFeedback, MotorProtocol
from .dji import DjiC620Protocol
from .mit import MitCommand, MitProtocol

#: Protocol classes by ``can.protocol`` name.
PROTOCOLS = {MitProtocol.name: MitProtocol, DjiC620Protocol.name: DjiC620Protocol}


def make_protocol(name: str, **params) -> MotorProtocol:
    """Build protocol ``name`` ('mit' or 'dji_c620') with its constructor parameters."""
    try:
        cls = PROTOCOLS[name]
    except KeyError:
        raise ValueError('unknown CAN protocol %r (one of %s)'
                         % (name, ', '.join(sorted(PROTOCOLS)))) from None
    return cls(**params)


__all__ = ['DjiC620Protocol', 'Frame', 'make_protocol', 'MitCommand', 'MitProtocol',
           'MotorFeedback', 'MotorProtocol', 'PROTOCOLS']
