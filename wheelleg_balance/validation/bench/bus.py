"""
The benchmark's bus part: what the node's CAN traffic costs in CanIo alone, per transport.

On python-can's ``udp_multicast`` bus (between processes, in a kernel without SocketCAN) every
frame goes through msgpack and a UDP datagram, and the bus hands the node each of its own
frames back (nodes/can_io.py drops these echoes only after python-can has decoded them). The
robot's bus is SocketCAN: a 16-byte ``struct can_frame`` per frame and no echoes. This part
measures each path alone, so that a node figure can be read for another bus:

- ``udp_multicast``: CanIo on python-can's test bus (the node's own code and settings);
- ``socketcan_path``: CanIo as it runs on SocketCAN, on a python-can ``SocketcanBus`` over a
  pair of connected loopback UDP sockets (nodes/socketcan_hub.py): the frames straight on the
  bus's socket;
- ``socketcan_python_can``: the same through python-can's own recv and send (select, then
  ``capture_message``; ``build_can_frame``, select, send), CanIo's path before 2026-12-06.

The kernel's CAN stack (the driver, the TX queue) is in neither SocketCAN figure; the Python
side of every frame is.

Each transport runs in its own process: a DeadlineLoop at 2 ms (core/deadline.py, the node's
loop) polls the replies and sends the node's commands of one tick (``frames`` frames; the
six-motor node with its legs taking turns sends four); a peer process answers each command
with one 8-byte reply, as the motors do. The figures: the process's CPU [% of a core], the
wall time of poll + send per tick, frames and echoes per tick.

    python -m wheelleg_balance.validation.bench.bus TRANSPORT  # one of TRANSPORTS
        --duration S --frames N --output F.json [--group G --port P] [--warmup S]
"""
import argparse
import json
import math
import multiprocessing
import time
from typing import Dict

import can

from .stats import cpu_percent, proc_cpu_seconds, summary_us
from ...core.deadline import DeadlineLoop
from ...core.protocols.base import Frame
from ...nodes.can_io import CanIo, open_bus
from ...nodes.socketcan_hub import socketcan_pair

TRANSPORTS = ('udp_multicast', 'socketcan_path', 'socketcan_python_can')
PERIOD = 0.002
#: Seconds run before the measured window (the peer started, the caches warm).
WARMUP = 2.0
#: A reply's arbitration ID: the command's plus this (a reply never looks like an echo).
REPLY_OFFSET = 0x100


def answer(bus: can.BusABC, stop) -> None:
    """Answer every command (an ID below REPLY_OFFSET) with one 8-byte reply, until ``stop``."""
    try:
        while not stop.is_set():
            msg = bus.recv(0.05)
            if msg is not None and msg.arbitration_id < REPLY_OFFSET:
                bus.send(can.Message(arbitration_id=msg.arbitration_id + REPLY_OFFSET,
                                     data=bytes(8), is_extended_id=False), 0.01)
    finally:
        bus.shutdown()


def run_io(transport: str, duration: float, frames: int = 4, group: str = '239.74.163.99',
           port: int = 45699, warmup: float = WARMUP) -> Dict:
    """Run CanIo at 500 Hz on ``transport`` with a peer answering; its figures (module doc)."""
    if transport not in TRANSPORTS:
        raise ValueError('transport must be one of %s' % ', '.join(TRANSPORTS))
    if transport == 'udp_multicast':
        ours, theirs = open_bus('udp_multicast', group, port), None
    else:
        ours, theirs = socketcan_pair()
    ctx = multiprocessing.get_context('fork')   # the peer inherits its end of the pair
    stop = ctx.Event()
    peer = ctx.Process(target=_peer, args=(theirs, group, port, stop), daemon=True)
    peer.start()
    if theirs is not None:
        theirs.shutdown()   # the peer's end, in this process (the peer has its own copy)
    # The peer answers through python-can's SocketcanBus code either way.
    io = CanIo(ours, raw_frames=transport != 'socketcan_python_can')
    commands = [Frame(k + 1, bytes([k + 1] * 8), False) for k in range(frames)]
    received = []
    spans = []
    start = time.monotonic()
    window = {}
    errors = []

    def on_error(now_ns: int, exc: BaseException) -> None:
        errors.append('%s: %s' % (type(exc).__name__, exc))
        loop.stop()

    loop = DeadlineLoop(PERIOD, on_error=on_error)
    clock = time.perf_counter_ns

    def tick(now_ns: int) -> None:
        t0 = clock()
        received.clear()
        io.poll(received)
        error = io.send(commands)
        t1 = clock()
        elapsed = time.monotonic() - start
        if elapsed >= warmup:
            if not window:
                window.update(cpu=proc_cpu_seconds(), wall=time.monotonic(), ticks=loop.ticks,
                              counters=io.counters())
            spans.append(t1 - t0)
        if error is not None and window:
            window['send_error'] = error
        if elapsed >= warmup + duration:
            loop.stop()

    try:
        loop.run(tick)
        cpu, wall = proc_cpu_seconds(), time.monotonic()
        end = io.counters()
    finally:
        stop.set()
        peer.join(timeout=5.0)
        if peer.is_alive():
            peer.kill()
        io.close()
    if errors:
        raise RuntimeError('the bus loop failed: %s' % errors[0])
    ticks = loop.ticks - window['ticks']
    begin = window['counters']
    per_tick = {k: (end[k] - begin[k]) / max(ticks, 1)
                for k in ('tx_frames', 'rx_frames', 'rx_echoes', 'tx_errors', 'rx_errors')}
    io_us = summary_us(spans)
    return {'transport': transport, 'frames': frames, 'duration_s': wall - window['wall'],
            'ticks': ticks, 'cpu_percent': cpu_percent(window['cpu'], cpu, wall - window['wall']),
            'io_median_us': io_us['median_us'], 'io_p99_us': io_us['p99_us'],
            'io_mean_us': sum(spans) / len(spans) / 1e3 if spans else math.nan,
            'per_tick': per_tick, 'send_error': window.get('send_error', '')}


def _peer(theirs, group: str, port: int, stop) -> None:
    bus = open_bus('udp_multicast', group, port) if theirs is None else theirs
    answer(bus, stop)


def frames_per_tick(divider: int, wheels: int = 2, hips: int = 4) -> int:
    """Return the commands per balancing tick, on average (each hip every divider-th tick)."""
    return wheels + int(round(hips / max(1, divider)))


def node_cpu_on_socketcan(node_cpu: float, bus: Dict, path: str = 'socketcan_path') -> float:
    """
    Estimate the node's CPU on SocketCAN [% of a core] (NaN when a figure is missing).

    Its CPU on the test bus, less the test bus's CanIo cost, plus ``path``'s: socketcan_path
    (the node's code) or socketcan_python_can (through python-can's recv and send).
    """
    try:
        udp = bus['udp_multicast']['cpu_percent']
        other = bus[path]['cpu_percent']
    except (KeyError, TypeError):
        return math.nan
    return float(node_cpu) - float(udp) + float(other)


def main(argv=None) -> int:
    """Run one transport and write its figures as JSON (see the module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('transport', choices=TRANSPORTS)
    parser.add_argument('--duration', type=float, required=True, help='seconds measured')
    parser.add_argument('--frames', type=int, default=4, help='commands per tick')
    parser.add_argument('--output', required=True, help='JSON path')
    parser.add_argument('--group', default='239.74.163.99', help='udp_multicast group')
    parser.add_argument('--port', type=int, default=45699, help='udp_multicast port')
    parser.add_argument('--warmup', type=float, default=WARMUP, help='seconds before the window')
    args = parser.parse_args(argv)
    result = run_io(args.transport, args.duration, args.frames, args.group, args.port,
                    args.warmup)
    with open(args.output, 'w') as f:
        json.dump(result, f)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
