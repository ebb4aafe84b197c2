"""The XM430-W350 control table against the e-manual's tables, and its unit conversions."""

from __future__ import annotations

import math

import pytest

from protocol import mx28, xm430


@pytest.mark.parametrize(
    ("name", "address", "size", "access", "default"),
    [
        # e-manual xm430-w350 "Control Table of EEPROM Area"
        ("model_number", 0, 2, "r", 1020),
        ("id", 7, 1, "rw", 1),
        ("operating_mode", 11, 1, "rw", 3),
        ("homing_offset", 20, 4, "rw", 0),
        ("current_limit", 38, 2, "rw", 1193),
        ("velocity_limit", 44, 4, "rw", 200),  # from firmware V42 (protocol/xm430.py)
        ("max_position_limit", 48, 4, "rw", 4095),
        ("shutdown", 63, 1, "rw", 52),
        # "Control Table of RAM Area"
        ("torque_enable", 64, 1, "rw", 0),
        ("hardware_error_status", 70, 1, "r", 0),
        ("position_p_gain", 84, 2, "rw", 800),
        ("goal_current", 102, 2, "rw", None),
        ("profile_velocity", 112, 4, "rw", 0),
        ("goal_position", 116, 4, "rw", None),
        ("moving_status", 123, 1, "r", 0),
        ("present_current", 126, 2, "r", None),
        ("present_position", 132, 4, "r", None),
        ("present_temperature", 146, 1, "r", None),
    ],
)
def test_items_as_in_the_e_manual(
    name: str, address: int, size: int, access: str, default: int | None
) -> None:
    it = xm430.item(name)
    assert (it.address, it.size, it.access, it.default) == (address, size, access, default)
    assert it.area == ("eeprom" if address < 64 else "ram")


def test_model_and_layout() -> None:
    assert xm430.MODEL_NUMBER == 1020
    assert xm430.TABLE_END == 147
    assert "present_load" not in xm430.TABLE and "present_load" in mx28.TABLE
    # items never overlap and the address index is complete
    spans = sorted((it.address, it.address + it.size) for it in xm430.TABLE.values())
    assert all(a_end <= b for (_, a_end), (b, _) in zip(spans, spans[1:], strict=False))
    assert set(xm430.BY_ADDRESS) == {it.address for it in xm430.TABLE.values()}
    # shared with the MX-28(2.0): everything but the current items sits at the same address
    for name, it in xm430.TABLE.items():
        if name in mx28.TABLE:
            assert mx28.TABLE[name].address == it.address and mx28.TABLE[name].size == it.size


def test_unit_conversions() -> None:
    assert xm430.to_unit(xm430.item("goal_position"), 2048) == pytest.approx(180.224)
    assert xm430.to_unit(xm430.item("present_current"), 1193) == pytest.approx(3209.17)
    assert xm430.to_unit(xm430.item("id"), 5) is None
    assert xm430.rad_per_tick() * 4096 == pytest.approx(2 * math.pi)
    assert xm430.rad_s_per_unit() == pytest.approx(0.229 * 2 * math.pi / 60)
    assert xm430.no_load_rpm(12.0) == pytest.approx(46.0)
    assert xm430.no_load_rpm(11.1) == pytest.approx(43.0)
    assert xm430.no_load_rpm(14.8) == pytest.approx(57.0)
    assert xm430.no_load_rpm(13.4) == pytest.approx(51.5)


def test_unknown_names() -> None:
    with pytest.raises(KeyError, match="present_current"):
        xm430.item("current")
    with pytest.raises(ValueError, match="overload"):
        xm430.hardware_error_bits("melting")
    assert xm430.hardware_error_names(xm430.hardware_error_bits(["overload", "overheating"])) \
        == ["overheating", "overload"]
