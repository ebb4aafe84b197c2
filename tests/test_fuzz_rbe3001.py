"""Malformed input at the RBE3001 codec and firmware simulator: DecodeError or silence."""

from __future__ import annotations

import struct

from hypothesis import given, settings
from hypothesis import strategies as st

from app.arms.rbe3001.sim import Rbe3001Firmware
from protocol.rbe3001 import DecodeError, decode_command, decode_packet, decode_reply

ANY_BYTES = st.binary(min_size=0, max_size=200)
# Well-framed packets with a known id and arbitrary floats reach the field checks.
FRAMED = st.builds(
    lambda cid, body: struct.pack("<I", cid) + body,
    st.sampled_from([37, 38, 39, 40, 41, 0, 0xFFFFFFFF]),
    st.binary(min_size=60, max_size=60),
)
REQUEST = st.sampled_from([37, 38, 39, 40, 7])


@settings(max_examples=300, deadline=None)
@given(data=ANY_BYTES | FRAMED, request=REQUEST)
def test_decoders_only_raise_decode_error(data: bytes, request: int) -> None:
    for decode in (decode_packet, decode_command, lambda d: decode_reply(request, d)):
        try:
            decode(data)
        except DecodeError:
            pass


@settings(max_examples=200, deadline=None)
@given(chunks=st.lists(ANY_BYTES | FRAMED, max_size=8))
def test_firmware_receive_never_raises(chunks: list[bytes]) -> None:
    fw = Rbe3001Firmware()
    now = 0.0
    for chunk in chunks:
        now += 0.01
        for delay, reply in fw.receive(chunk, now):
            assert delay >= 0.0
            assert len(reply) == 64
