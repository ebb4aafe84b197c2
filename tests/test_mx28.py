"""protocol/mx28.py against the MX-28 (2.0) control table (e-manual, reference file)."""

from __future__ import annotations

import pytest

from protocol import mx28


@pytest.mark.parametrize(("name", "address", "size", "default", "access"), [
    ("model_number", 0, 2, 30, "r"),
    ("id", 7, 1, 1, "rw"),
    ("baud_rate", 8, 1, 1, "rw"),
    ("return_delay_time", 9, 1, 250, "rw"),
    ("operating_mode", 11, 1, 3, "rw"),
    ("homing_offset", 20, 4, 0, "rw"),
    ("temperature_limit", 31, 1, 80, "rw"),
    ("max_voltage_limit", 32, 2, 160, "rw"),
    ("min_voltage_limit", 34, 2, 95, "rw"),
    ("pwm_limit", 36, 2, 885, "rw"),
    ("velocity_limit", 44, 4, 230, "rw"),  # 230 from firmware V42
    ("max_position_limit", 48, 4, 4095, "rw"),
    ("min_position_limit", 52, 4, 0, "rw"),
    ("shutdown", 63, 1, 52, "rw"),
    ("torque_enable", 64, 1, 0, "rw"),
    ("status_return_level", 68, 1, 2, "rw"),
    ("hardware_error_status", 70, 1, 0, "r"),
    ("velocity_i_gain", 76, 2, 1920, "rw"),
    ("velocity_p_gain", 78, 2, 100, "rw"),
    ("position_p_gain", 84, 2, 850, "rw"),
    ("profile_acceleration", 108, 4, 0, "rw"),
    ("profile_velocity", 112, 4, 0, "rw"),
    ("goal_position", 116, 4, None, "rw"),
    ("moving", 122, 1, 0, "r"),
    ("moving_status", 123, 1, 0, "r"),
    ("present_load", 126, 2, None, "r"),
    ("present_velocity", 128, 4, None, "r"),
    ("present_position", 132, 4, None, "r"),
    ("present_input_voltage", 144, 2, None, "r"),
    ("present_temperature", 146, 1, None, "r"),
])
def test_spot_checks(name: str, address: int, size: int, default: int | None, access: str) -> None:
    it = mx28.item(name)
    assert (it.address, it.size, it.default, it.access) == (address, size, default, access)
    assert mx28.BY_ADDRESS[address] is it
    assert it.area == ("eeprom" if address < 64 else "ram")


def test_every_item_of_the_reference_is_there() -> None:
    assert len(mx28.TABLE) == 50
    assert mx28.MODEL_NUMBER == 30
    assert mx28.TABLE_END == 147


def test_items_do_not_overlap_and_fit_their_ranges() -> None:
    items = sorted(mx28.TABLE.values(), key=lambda it: it.address)
    for a, b in zip(items, items[1:], strict=False):
        assert a.address + a.size <= b.address, (a.name, b.name)
    for it in items:
        assert it.size in (1, 2, 4)
        lo = -(1 << (8 * it.size - 1)) if it.signed else 0
        hi = (1 << (8 * it.size - 1)) - 1 if it.signed else (1 << (8 * it.size)) - 1
        assert lo <= it.min_raw <= it.max_raw <= hi, it.name
        if it.default is not None:
            assert it.min_raw <= it.default <= it.max_raw, it.name


def test_ranges_of_goal_items() -> None:
    goal = mx28.item("goal_position")
    assert (goal.min_raw, goal.max_raw) == (-1_048_575, 1_048_575)
    assert mx28.item("goal_position").signed and mx28.item("present_load").signed
    assert (mx28.item("present_load").min_raw, mx28.item("present_load").max_raw) == (-1000, 1000)
    offset = mx28.item("homing_offset")
    assert (offset.min_raw, offset.max_raw) == (-1_044_479, 1_044_479)


def test_units() -> None:
    assert mx28.to_unit(mx28.item("present_position"), 4096) == pytest.approx(360.448)
    assert mx28.to_unit(mx28.item("goal_position"), -1000) == pytest.approx(-88.0)
    assert mx28.to_unit(mx28.item("profile_velocity"), 100) == pytest.approx(22.9)
    assert mx28.item("profile_velocity").unit == "rpm"
    assert mx28.to_unit(mx28.item("profile_acceleration"), 2) == pytest.approx(429.154)
    assert mx28.item("profile_acceleration").unit == "rev/min^2"
    assert mx28.to_unit(mx28.item("present_load"), -125) == pytest.approx(-12.5)
    assert mx28.item("present_load").unit == "percent"
    assert mx28.to_unit(mx28.item("present_input_voltage"), 120) == pytest.approx(12.0)
    assert mx28.to_unit(mx28.item("return_delay_time"), 250) == pytest.approx(500.0)
    assert mx28.item("return_delay_time").unit == "us"
    assert mx28.item("present_temperature").unit == "C"
    assert mx28.to_unit(mx28.item("model_number"), 30) is None


def test_item_lookup_errors_are_helpful() -> None:
    assert mx28.item("Goal Position") is mx28.TABLE["goal_position"]
    with pytest.raises(KeyError, match="goal_pwm, goal_velocity, goal_position"):
        mx28.item("goal")
    with pytest.raises(KeyError, match="mx-28-2"):
        mx28.item("torque")
