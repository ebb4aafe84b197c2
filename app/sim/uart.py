"""What a UART reads from a byte stream sent at another baud rate (sans-IO, pure): `resample`.

Every simulated device behind a real byte stream can use it where the sender's and the
receiver's rates differ (the simulated Dynamixel bus on a pseudo-terminal, whose host sets a
termios rate: app/arms/dynamixel/sim_bus.py).

The line, 8N1 as the Dynamixel bus runs it (e-manual MX-28(2.0): "8bit, 1stop, No Parity"):
idle high; each byte a start bit (low), eight data bits least significant first, a stop bit
(high), each 1/rate seconds, back to back. The receiver does what a UART does: it waits for a
falling edge, checks the start bit half a bit later (still low, or it was a glitch), samples
the data bits at the middles of its own bit times, 1.5 to 8.5 bit times after the edge, and
the stop bit at 9.5; then it looks for the next falling edge. Its bit times are its own rate's,
so a stream at another rate is sampled at the wrong places: wrong values, and more bytes (a
faster receiver finds start bits inside the sender's bytes) or fewer (a slower one spans
several of the sender's bytes with one frame). A stop bit sampled low is a framing error; the
byte is still delivered as sampled (Linux drivers/tty/n_tty.c `n_tty_receive_parity_error`:
without INPCK, which pyserial clears, "put_tty_queue(c, ...)"), and a frame that reads all low
is a break, delivered as 0x00 (`n_tty_receive_break`, IGNBRK and BRKINT clear). A few percent
apart both sides agree (the receiver's error reaches half a bit only at the stop bit of a byte,
about 5 %); the standard Dynamixel rates are a factor of 1.125 or more apart, so a stream at
one is garbage at another: a UART at twice the rate reads a 0xFF as 0xFE, at 17 times the rate
(1 Mbps reading 57,600) mostly 0x00 breaks, at a seventeenth (57,600 reading 1 Mbps) one or two
bytes for a whole packet.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterable


def _edges(data: bytes, bit_s: float) -> tuple[list[float], list[int]]:
    """The line as (times, levels): level[i] holds from times[i] until times[i + 1]; idle
    high before the first and after the last."""
    times: list[float] = [float("-inf")]
    levels: list[int] = [1]
    t = 0.0
    for byte in data:
        bits = [0, *((byte >> k) & 1 for k in range(8)), 1]
        for b in bits:
            if b != levels[-1]:
                times.append(t)
                levels.append(b)
            t += bit_s
    return times, levels


def resample(data: bytes | Iterable[int], tx_rate: float, rx_rate: float) -> bytes:
    """The bytes a UART at `rx_rate` (bit/s) reads from `data` sent back to back at
    `tx_rate`, starting from an idle line; `data` itself when the rates are equal."""
    data = bytes(data)
    if tx_rate == rx_rate or not data:
        return data
    times, levels = _edges(data, 1.0 / tx_rate)

    def level(t: float) -> int:
        return levels[bisect_right(times, t) - 1]

    rx_bit = 1.0 / rx_rate
    out = bytearray()
    k = 1  # index of the next edge to consider
    while k < len(times):
        if levels[k] != 0:  # a rising edge: not a start
            k += 1
            continue
        edge = times[k]
        if level(edge + 0.5 * rx_bit):  # the start bit is gone at its middle: a glitch
            k += 1
            continue
        value = 0
        for bit in range(8):
            value |= level(edge + (1.5 + bit) * rx_bit) << bit
        out.append(value)  # a framing error (stop sampled low) or a break: delivered as read
        stop = edge + 9.5 * rx_bit
        k = bisect_right(times, stop)  # the next falling edge after the stop bit's sample
    return bytes(out)
