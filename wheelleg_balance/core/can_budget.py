"""
The CAN bus budget: bits on the wire per frame, the load of a bus, the largest burst it queues.

A classical CAN data frame (ISO 11898-1) with a standard 11-bit identifier and n data bytes is
SOF 1 + identifier 11 + RTR 1 + IDE 1 + r0 1 + DLC 4 + data 8n + CRC 15 + CRC delimiter 1 +
ACK 2 + EOF 7 = 44 + 8n bits, plus 3 bits of interframe space; an extended (29-bit) identifier
adds SRR and 18 identifier bits (64 + 8n). Bit stuffing (a complemented bit after five equal
ones) covers SOF to the CRC, 34 + 8n bits for a standard frame, and adds at most
floor((34 + 8n - 1) / 4) bits. ``frame_bits`` returns that worst case, so a load figure is an
upper bound: an MIT command (8 bytes) takes at most 135 bit times, a reply (6 bytes) 115, and six
of each per 2 ms tick 750 kbit/s, 75 % of a 1 Mbit/s bus (four of each, the hips at 250 Hz by
``legs.command_divider``: 50 %).
"""
from functools import lru_cache
from typing import Iterable, Optional

#: Frame bits outside the data field, interframe space included (standard, extended id).
_OVERHEAD_BITS = {False: 47, True: 67}
#: Bits covered by bit stuffing outside the data field (SOF .. CRC).
_STUFFED_BITS = {False: 34, True: 54}


@lru_cache(maxsize=None)   # counted for every frame sent and received: a few dozen keys
def frame_bits(dlc: int, extended: bool = False) -> int:
    """Return the bit times [bit] a classical data frame of ``dlc`` bytes takes at most."""
    n = 8 * max(0, min(8, int(dlc)))
    return _OVERHEAD_BITS[extended] + n + (_STUFFED_BITS[extended] + n - 1) // 4


def frames_bits(sizes: Iterable[int], extended: bool = False) -> int:
    """Return the bit times of frames with these data lengths (worst-case stuffing)."""
    return sum(frame_bits(n, extended) for n in sizes)


def max_catch_up(tx_queue_len: int, frames_per_tick: int, wanted: int) -> int:
    """
    Return how many missed ticks may be served back to back with a TX queue this long.

    A catch-up sends the frames of every missed tick and of the current one at once; more than
    ``tx_queue_len`` frames (the interface's txqueuelen) would overflow the kernel's queue and
    fail the sends. At most ``wanted``; 0 when one tick's frames fill the queue already.
    """
    if frames_per_tick <= 0:
        return wanted
    return max(0, min(wanted, tx_queue_len // frames_per_tick - 1))


class BusLoad:
    """
    The load of one bus from the bits it carried, over the time between two ``update`` calls.

    bitrate [bit/s]. ``update(now, bits)`` takes the bits counted so far (sent and received)
    and returns the load [%] since the previous call (None on the first).
    """

    def __init__(self, bitrate: float):
        self.bitrate = float(bitrate)
        self._mark: Optional[tuple] = None
        self.load_pct: Optional[float] = None

    def update(self, now: float, bits: int) -> Optional[float]:
        """Return the load [%] of the bus since the previous call; remember this one."""
        if self._mark is not None:
            t0, b0 = self._mark
            if now > t0:
                self.load_pct = 100.0 * (bits - b0) / (self.bitrate * (now - t0))
        self._mark = (now, bits)
        return self.load_pct
