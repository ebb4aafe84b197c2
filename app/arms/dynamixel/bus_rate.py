"""What a Dynamixel bus carries: the wire time of one poll at a baud rate, the poll rate that
fits, and, at connect, a scan of the other baud rates when nothing answers at the profile's.

Wire time (Protocol 2.0, https://emanual.robotis.com/docs/en/dxl/protocol2/): an instruction
packet is header (4) + ID + LEN (2) + instruction + parameters + CRC (2) bytes; a status packet
header (4) + ID + LEN (2) + 0x55 + error + data + CRC (2). The poll is one SYNC_READ of
`POLL_LEN` bytes from n servos: 14 + n bytes out, n * (11 + POLL_LEN) back, 10 bits a byte
(8N1: start, 8 data, stop; e-manual "Protocol Type": 8 bit, 1 stop, no parity), and each
servo waits its Return Delay Time (9) before answering (e-manual, default 250 = 500 us). At
57,600 bps four MX-28s take about 21 ms a poll, so the profile's 200 Hz cannot be carried:
the driver polls at what fits (`bus_poll_hz`) and says so.
"""

from __future__ import annotations

import math

#: Bytes read per servo by the poll: Moving (122) .. Present Position (132..135).
POLL_LEN = 14
#: Share of the bus polls may take; the rest carries requests (goals, reads) between them.
POLL_BUS_SHARE = 0.8
#: Return Delay Time a servo ships with (e-manual: Return Delay Time (9) initial 250, 2 us).
DEFAULT_RETURN_DELAY_US = 500.0
#: Rates a servo may be at (Baud Rate (8) codes 0..7, e-manual "Baud Rate(8)"), the factory
#: rate first.
OTHER_RATES = (57_600, 1_000_000, 115_200, 9_600, 2_000_000, 3_000_000, 4_000_000, 4_500_000)


def poll_bytes(n_servos: int, data_len: int = POLL_LEN) -> int:
    """Bytes on the wire for one SYNC_READ of `data_len` bytes from `n_servos`, both ways."""
    return (14 + n_servos) + n_servos * (11 + data_len)


def poll_cost_s(n_servos: int, baudrate: int, return_delay_us: float | None) -> float:
    """Seconds the bus is busy for one poll: its bytes at 10 bits each, and every servo's
    Return Delay Time (the e-manual's default where the profile sets none)."""
    delay = DEFAULT_RETURN_DELAY_US if return_delay_us is None else return_delay_us
    return poll_bytes(n_servos) * 10.0 / baudrate + n_servos * delay * 1e-6


def bus_poll_hz(n_servos: int, baudrate: int, return_delay_us: float | None) -> float:
    """The fastest poll rate the bus carries with `POLL_BUS_SHARE` of its time, Hz."""
    return POLL_BUS_SHARE / poll_cost_s(n_servos, baudrate, return_delay_us)


def poll_rate(wanted_hz: float, n_servos: int, baudrate: int,
              return_delay_us: float | None) -> tuple[float, str | None]:
    """The poll rate to use (the profile's, or the bus's limit, whole Hz, when lower) and the
    warning that names it (None when the profile's fits)."""
    limit = bus_poll_hz(n_servos, baudrate, return_delay_us)
    if wanted_hz <= limit:
        return wanted_hz, None
    hz = max(1.0, float(math.floor(limit)))
    cost = poll_cost_s(n_servos, baudrate, return_delay_us) * 1000.0
    return hz, (f"a poll of {n_servos} servos takes {cost:.1f} ms on the bus at {baudrate:,} "
                f"bps ({poll_bytes(n_servos)} bytes, 10 bits each, and the return delays): "
                f"polling at {hz:g} Hz, not the profile's {wanted_hz:g} Hz (raise the baud rate "
                "with armserver setup-servos, or lower link.poll_hz)")


def found_message(rates: dict[int, list[int]], profile_rate: int,
                  garbled: list[int] | tuple[int, ...] = ()) -> str:
    """What a connect scan found, for the arm's detail and the log; `garbled`: the rates
    where bytes came that were no packet (what a UART reads of a servo at another rate),
    told apart from silence."""
    noise = (f" (garbled answers at {', '.join(f'{r:,}' for r in garbled)} bps: a UART at "
             "another rate than the servo's reads its replies as garbage)" if garbled else "")
    if not rates:
        return (f"no servo answers at {profile_rate:,} bps nor at any other standard rate"
                f"{noise} (check power, the cable and the adapter)")
    parts = [f"{rate:,} bps (ID {', '.join(map(str, ids))})" for rate, ids in rates.items()]
    first = next(iter(rates))
    return (f"no servo answers at the profile's {profile_rate:,} bps{noise}; servos answer at "
            f"{'; '.join(parts)}: run armserver setup-servos, or set link.baudrate = {first}")
