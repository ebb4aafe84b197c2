"""The refusal of a torque off that would let gravity move an arm: the joints its profile
says fall without torque (`falls_without_torque`: the angler's z winch, an OpenManipulator-X's
shoulder, elbow and wrist) go where no planned move may go unless someone holds them or their
load rests. A teleoperation session that frees its leader and `PUT /arms/{arm}/torque` ask the
same question, `load_supported` (a reboot asks it of one servo: app/arms/dynamixel/api.py)."""

from __future__ import annotations

from app.errors import InUse


def falling_refusal(arm: str, falls: list[str], doing: str, also: str = "") -> InUse:
    """409 `in_use` for `doing` (what switches `arm`'s torque off) where `falls` (the
    profile's `falling_joints`) would fall; `also`: another way out, said after the flag."""
    one = len(falls) == 1
    return InUse(f"{doing} switches {arm}'s torque off, and {', '.join(falls)} "
                 f"{'falls' if one else 'fall'} without torque (the profile's "
                 "joints.falls_without_torque): gravity would move "
                 f"{'it' if one else 'them'} where no planned move may go. Hold "
                 f"{'it' if one else 'them'} (or rest the load), then say so: "
                 '{"load_supported": true}' + also)
