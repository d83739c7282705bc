"""
The SocketCAN interface's settings from ``ip -details -json link show <channel>`` (pure).

iproute2 prints one JSON object per interface: ``operstate`` and ``flags`` (``UP``),
``txqlen``, ``link_type`` (``can``), and under ``linkinfo.info_data`` (kind ``can``) the
controller's ``state`` (ERROR-ACTIVE, ERROR-WARNING, ERROR-PASSIVE, BUS-OFF, STOPPED),
``restart_ms`` and ``bittiming.bitrate`` (absent until a bitrate was set). The robot wants
(docs/robot_setup.md, "The CAN interface"): up, 1 Mbit/s, restart-ms > 0 (the kernel restarts
the controller after a bus-off by itself) and a TX queue long enough for a tick's frames
(txqueuelen 1000; SocketCAN's default is 10). ``check_link`` returns the findings with the
exact ``ip link set`` lines that are missing; bitrate and restart-ms can only change while the
interface is down, so those fixes take it down and up again.
"""
import json
import shlex
import subprocess
from typing import List, Optional

from .report import Check, FAIL, INFO, PASS, WARN

#: What the robot's buses need.
BITRATE = 1000000
RESTART_MS = 100
TXQUEUELEN = 1000
#: Controller states in which frames still flow (ERROR-WARNING: errors seen, still sending).
GOOD_STATES = ('ERROR-ACTIVE', 'ERROR-WARNING')


def ip_link_json(channel: str, run=subprocess.run) -> Optional[str]:
    """Return the text of ``ip -details -json link show <channel>``, or None if ip failed."""
    try:
        out = run(['ip', '-details', '-json', 'link', 'show', channel], capture_output=True,
                  text=True, timeout=5.0)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout if out.returncode == 0 else None


def check_link(text: Optional[str], channel: str, bitrate: int = BITRATE,
               restart_ms: int = RESTART_MS, txqueuelen: int = TXQUEUELEN) -> List[Check]:
    """Judge ``ip -details -json link show <channel>`` output (None: no such interface)."""
    item = channel
    q = shlex.quote(channel)
    retype = ['sudo ip link set %s down' % q,
              'sudo ip link set %s type can bitrate %d restart-ms %d' % (q, bitrate, restart_ms),
              'sudo ip link set %s up' % q]
    setup = retype[:2] + ['sudo ip link set %s txqueuelen %d' % (q, txqueuelen), retype[2]]
    try:
        info = json.loads(text)[0] if text else None
    except (ValueError, IndexError, KeyError, TypeError):
        info = None
    if not isinstance(info, dict):
        return [Check(FAIL, item, 'no such network interface (no SocketCAN adapter, or it is '
                      'named otherwise: `ip link show` lists them; a USB adapter needs its '
                      'driver, e.g. gs_usb or peak_usb)', setup)]
    data = (info.get('linkinfo') or {}).get('info_data') or {}
    kind = (info.get('linkinfo') or {}).get('info_kind')
    if info.get('link_type') != 'can' and kind not in ('can', 'vcan'):
        return [Check(FAIL, item, 'is not a CAN interface (link type %s)'
                      % info.get('link_type'))]
    if kind == 'vcan':
        up = 'UP' in info.get('flags', [])
        return [Check(WARN, item, 'is a virtual CAN interface (vcan): no bus, no motors' +
                      ('' if up else ', and it is down'),
                      [] if up else ['sudo ip link set %s up' % q])]
    out: List[Check] = []
    rate = (data.get('bittiming') or {}).get('bitrate')
    if rate != bitrate:
        out.append(Check(FAIL, item, 'bitrate is %s, the motors speak %d bit/s' % (
            'not set' if rate is None else '%d bit/s' % rate, bitrate)))
    r_ms = data.get('restart_ms')
    if not r_ms:
        out.append(Check(FAIL, item, 'restart-ms is %s: after a bus-off (a loose connector, a '
                         'missing terminator) the interface stays off until someone takes it '
                         'down and up again' % ('0 (off)' if r_ms == 0 else 'unknown')))
    # Both need the interface down: one fix line set, on the last of the two findings.
    retyped = bool(out)
    if retyped:
        out[-1] = Check(FAIL, item, out[-1].text, retype)
    qlen = info.get('txqlen')
    if not isinstance(qlen, int) or qlen < txqueuelen:
        out.append(Check(FAIL, item, 'txqueuelen is %s: a busy bus fills so short a queue within '
                         'a tick and every send then fails (CanOperationError: a CAN fault)'
                         % qlen, ['sudo ip link set %s txqueuelen %d' % (q, txqueuelen)]))
    up = 'UP' in info.get('flags', []) or info.get('operstate') == 'UP'
    state = data.get('state')
    if not up:
        out.append(Check(FAIL, item, 'is down', [] if retyped else
                         ['sudo ip link set %s up' % q]))
    elif state not in GOOD_STATES:
        out.append(Check(FAIL, item, 'controller state %s: %s' % (state, {
            'BUS-OFF': 'too many errors, the controller stopped sending (wiring, termination, '
                       'a wrong bitrate, or a motor unpowered)',
            'ERROR-PASSIVE': 'many errors (no other node acknowledges: motors unpowered, '
                             'CAN_H/CAN_L swapped, termination missing)',
            'STOPPED': 'the controller is stopped'}.get(state, 'unknown')),
            ['sudo ip link set %s down' % q, 'sudo ip link set %s up' % q]))
    if not out:
        out.append(Check(PASS, item, 'up, %d bit/s, restart-ms %d, txqueuelen %d, %s'
                         % (rate, r_ms, qlen, state)))
    elif state == 'ERROR-WARNING':
        out.append(Check(INFO, item, 'controller state ERROR-WARNING: errors were counted '
                         '(berr tx %s, rx %s)' % ((data.get('berr_counter') or {}).get('tx'),
                                                  (data.get('berr_counter') or {}).get('rx'))))
    return out
