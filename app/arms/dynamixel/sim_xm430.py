"""One simulated XM430-W350 (the OpenManipulator-X's servo): the MX-28 model on the XM430's
control table.

Source: the XM430-W350 e-manual, https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/
(control table, "Specifications"); protocol/xm430.py holds the table. Everything the MX-28
simulator does (app/arms/dynamixel/sim_mx28.py: write checks, faults, REBOOT, the profile generator
and the motor that follows it) holds here unchanged; what differs is data:

- Model Number 1020, the XM430's defaults (Velocity Limit 200, Position P Gain 800) and
  no-load speed (46 rpm at 12 V, 43 at 11.1 V, 57 at 14.8 V).
- Operating Mode also takes 0 (current) and 5 (current-based position). Mode 5 runs the
  profile generator as extended position (multi-turn), the Current Limit acting only as the
  bound on Goal Current. Mode 0 is modelled as the PWM mode with the duty Goal Current /
  Current Limit: an unloaded motor under a constant current runs up to its no-load speed,
  which is all this simulator models (no load torque). Both are our simplifications.
- Goal Current beyond Current Limit is refused with the data limit error, as Goal PWM beyond
  PWM Limit ("Goal Current(102)": range -Current Limit ~ Current Limit).
- Present Current (126) instead of Present Load: the load model (0.1 % of the stall torque)
  scaled to the stall current, 2.3 A at 12 V (about 2.69 mA a unit).
"""

from __future__ import annotations

from app.arms.dynamixel import sim_mx28 as mx28_servo
from app.arms.dynamixel.sim_mx28 import EXTENDED, POSITION, PWM, VELOCITY, Mx28Servo
from protocol import xm430

CURRENT = 0
CURRENT_POSITION = 5
FIRMWARE_VERSION = 46


class Xm430Servo(Mx28Servo):
    """An XM430-W350 on the simulated bus."""

    spec = xm430
    modes = (CURRENT, VELOCITY, POSITION, EXTENDED, CURRENT_POSITION, PWM)
    position_modes = (POSITION, EXTENDED, CURRENT_POSITION)
    limits = {**mx28_servo._LIMITS, "goal_current": "current_limit"}
    firmware_version = FIRMWARE_VERSION

    def _drive(self) -> float:
        if self.get("operating_mode") == CURRENT:
            limit = self.get("current_limit")
            return self.get("goal_current") / limit if limit else 0.0
        return super()._drive()

    def _publish_load(self, load: int) -> None:
        amps = load / 1000.0 * xm430.STALL_CURRENT_A
        self.set("present_current", round(amps / xm430.CURRENT_A_PER_UNIT))

    def _ram_defaults(self) -> None:
        super()._ram_defaults()
        self.set("goal_current", self.get("current_limit"))
