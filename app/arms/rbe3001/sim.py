"""A simulated RBE3001 Gen A firmware: the same 64-byte packets as the Nucleo, a 400 Hz PID
loop per joint and simple joint dynamics, so the driver cannot tell it from the arm.

Behaviour copied from WPIRoboticsEngineering/RBE3001_nucleo_firmware (see
/work/shared/reference/rbe3001.md):
- SET_PID (PidServer.cpp): setpoint of joint i in float[3i]; a setpoint within 0.01 tick of
  the last one is ignored (so re-sending is a status poll); the reply buffer is zeroed, then
  float[3i] position, [3i+1] velocity (ticks/s), [3i+2] load-cell ADC (0..1).
- STATUS (this team's id 38): positions 0-2, velocities 3-5, ADC 6-8.
- SET_GAIN: disable that joint's controller, set kp/ki/kd, re-enable (integral and
  derivative history cleared). SET_CLAW: claw setpoint 0..1.
- Every reply zeroes the whole float area first, as PidServer.cpp ("re-initialize the packet
  to all zeros"): SET_GAIN and SET_CLAW replies are the id and fifteen zero floats. With
  `echo=True` (profile `[link] sim_echo`), as builds that echo: STATUS leaves floats 9-14 as
  received, SET_GAIN and SET_CLAW send the request back unchanged.
- Unknown ids, packets that are not 64 bytes and packets with out-of-range fields: silence.
- Firmware builds (profile `[link] sim_firmware`): `status` serves STATUS (38); `stock_99`
  answers it with SimplePacketComs' error packet (id 99, the unknown id in bytes 4-7), and
  `stock_silent` not at all, as builds without a STATUS server.
- SET_GAIN and SET_CLAW "do not provide any return values" (design document): `[link]
  sim_gain_claw_reply` = `zeros` (PidServer's zeroed buffer, or the echo with `sim_echo`),
  `echo`, `silent` (no reply) or `other` (bytes that are neither).
- Power-on (`[link] sim_power_on_pose`): the arm starts in that calibration pose and the
  encoders read zero there (src/main.cpp's `ZeroPID()` at start-up, "set the current encoder
  value to 0"); without it they read the profile's offsets. (Its USB serial number, the
  calibration's identity, is the profile's `[link] serial_number`, which the SimLink reports.)
- Encoder: whole ticks, firmware 4-sample moving average (so readings move in 1/4 ticks).
- Velocity: position difference over 61 PID cycles (~152 ms), stale between updates.
- Controller output: 0.5 +- 0.2 (clamped 0.3..0.7) from stop, kp 0.005, ki 0, kd 0. Each
  400 Hz cycle computes it as PID_Bowler's `RunAbstractPIDCalc` (WPIRoboticsEngineering/
  PID_Bowler, the firmware's `lib/PID_Bowler`): kp * e + kd * (e - e of the cycle before) +
  ki * (the running mean of e over about 20 cycles, zeroed as e changes sign); a new setpoint
  zeroes the mean and the error before (`InitAbsPIDWithPosition`); SET_GAIN keeps them.

Gain mapping (firmware units -> SI). The PID output `u` is a servo command around stop 0.5,
clamped to +-0.2; the sim reads it as the motor voltage fraction v = u / 0.2 of a geared DC
motor: torque = stall_torque * (v - omega / free_speed). With error e in ticks, kp in
output/tick, ki in output per tick of the error's mean, kd in output per tick of change
in a cycle (2.5 ms), the small-signal stiffness is
    K [N m/rad] = kp * (stall_torque / 0.2) * ticks_per_rev / (2 pi)
= 0.005 * 20 * 651.9 ~ 65 N m/rad for the defaults (4 N m stall): a 1 rad step runs at the
speed limit (~3 rad/s) and settles in ~0.4-0.6 s with back-EMF damping (zeta ~ 0.8) and a
gravity droop of a few ticks on the shoulder (the firmware's ki = 0 leaves it).

Joint convention (kinematics/rrr.py, the course notes): base q0 about the vertical;
shoulder q1 the elevation of link 2 above the horizontal; link 3 points along
(sin(q1 - q2), -cos(q1 - q2)) in the arm's vertical plane, so at q = 0 link 2 is level and
link 3 hangs straight down. ticks = offset + sign * q * tpr / (2 pi).
Strain ADC = offset + torque / scale (the profile's [force] table), averaged over 5 cycles.
The load cell sits between the gearbox and the link: it reads the torque the link carries
(holding it against gravity, and accelerating it), not the motor's, whose static friction it
does not see: at rest it reads minus the gravity torque exactly.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Sequence

from app.config import ArmProfile
from protocol.rbe3001 import (
    ERROR_ID,
    PACKET_SIZE,
    Ack,
    DecodeError,
    SetClaw,
    SetGain,
    SetPid,
    SetPidReply,
    Status,
    StatusReply,
    decode_command,
    encode_packet,
    encode_reply,
)

#: SimplePacketComs' error packet head: id 99, then the unknown id, both uint32.
ERROR_REPLY = struct.Struct("<II")
CYCLE_S = 0.0025  # firmware PID period since Jan 2018 (400 Hz)
VELOCITY_CYCLES = 61  # firmware velocity update period, cycles
ENCODER_AVERAGE = 4  # firmware moving average of the AS5050 reading, samples
STRAIN_AVERAGE = 5  # samples in the reported load-cell average
SETPOINT_DEADBAND_TICKS = 0.01  # PidServer ignores setpoints this close to the last one
OUTPUT_SPAN = 0.2  # output clamp 0.3..0.7 around stop 0.5
#: The firmware's integral is a running mean of the error over about this many cycles, not a
#: sum over time (WPIRoboticsEngineering/PID_Bowler src/PID_Bowler.cpp `RunAbstractPIDCalc`:
#: `integralTotal = error / integralSize + integralTotal * (integralSize - 1) / integralSize`,
#: `integralSize = 20.0` in `InitAbsPIDWithPosition`).
INTEGRAL_SIZE = 20.0
END_STOP_MARGIN = 0.3  # rad past each software limit where the mechanism stops the joint
MAX_CATCHUP_S = 2.0  # beyond this gap, older simulated time is skipped rather than computed
REPLY_DELAY_S = 0.0005  # firmware turnaround (the reference says round trip <= 2 ms)
ADC_STEPS = 4095  # 12-bit AnalogIn
GRAVITY = 9.81  # m/s^2

DEFAULT_GEOMETRY = (0.2032, 0.1651, 0.206375)  # l1, l2, l3 in m (design documents)


class Rbe3001Firmware:
    """SimDevice for the RBE3001 arm (packetised: one 64-byte packet a write)."""

    packetized = True

    def __init__(
        self,
        profile: ArmProfile | None = None,
        *,
        ticks_per_rev: Sequence[int] = (4096, 4096, 4096),
        offset_ticks: Sequence[float] = (0.0, 0.0, 0.0),
        sign: Sequence[int] = (1, 1, 1),
        geometry: Sequence[float] = DEFAULT_GEOMETRY,
        adc_scale: Sequence[float] = (5.0, 5.0, 5.0),
        adc_offset: Sequence[float] = (0.5, 0.5, 0.5),
        start_q: Sequence[float] = (0.0, 0.0, 0.0),
        link_masses: Sequence[float] = (0.25, 0.15, 0.10),
        stall_torque: float = 4.0,
        free_speed: float = 3.0,
        claw_rate: float = 2.0,
        echo: bool | None = None,
    ) -> None:
        """`link_masses` (kg): link 2, link 3, claw at the tip. `stall_torque` (N m) and
        `free_speed` (rad/s) are at the joint, after the gearbox. `claw_rate` in 1/s.
        `echo`: reply as an echoing build (None: the profile's `link.sim_echo`, else False)."""
        if echo is None:
            echo = profile.link.sim_echo if profile is not None else False
        self.echo = echo
        link = profile.link if profile is not None else None
        self.firmware = link.sim_firmware if link is not None else "status"
        self.gain_claw_reply = link.sim_gain_claw_reply if link is not None else "zeros"
        power_on = None
        if profile is not None and profile.link.sim_power_on_pose is not None:
            power_on = profile.calibration_poses[profile.link.sim_power_on_pose]
            start_q = power_on
        if profile is not None:
            ticks_per_rev = [j.ticks_per_rev for j in profile.joints]
            offset_ticks = [j.offset_ticks for j in profile.joints]
            sign = [j.sign for j in profile.joints]
            geometry = (profile.geometry["l1"], profile.geometry["l2"], profile.geometry["l3"])
            if profile.force is not None:
                adc_scale, adc_offset = profile.force.scale, profile.force.offset
        #: Mechanical end stops (rad): a little beyond the profile's limits where there is a
        #: profile, else half a turn each way. No gain or setpoint can spin a joint past them.
        stops = [(-math.pi, math.pi)] * 3
        if profile is not None:
            stops = [(j.min - END_STOP_MARGIN, j.max + END_STOP_MARGIN) for j in profile.joints]
        self.hard_stops = stops
        self.tpr = [float(t) for t in ticks_per_rev]
        self.offset = [float(o) for o in offset_ticks]
        self.sign = [float(s) for s in sign]
        self.l1, self.l2, self.l3 = (float(x) for x in geometry)
        self.adc_scale = [float(s) for s in adc_scale]
        self.adc_offset = [float(o) for o in adc_offset]
        self.m2, self.m3, self.m_tip = (float(m) for m in link_masses)
        self.stall_torque = stall_torque
        self.free_speed = free_speed
        self.claw_rate = claw_rate
        self.reflected_inertia = 0.01  # kg m^2, gearbox and motor seen at the joint
        self.viscous = 0.02  # N m s/rad, bearing friction besides the motor's back-EMF
        self.coulomb = 0.05  # N m

        self.q = [float(x) for x in start_q]  # rad
        if power_on is not None:  # ZeroPID() at start-up: the encoders read 0 here
            self.offset = [-self.sign[i] * self.q[i] * self.tpr[i] / (2 * math.pi)
                           for i in range(3)]
        self.qd = [0.0, 0.0, 0.0]  # rad/s
        self.torque = [0.0, 0.0, 0.0]  # motor torque at the joint, N m
        #: The torque the link carries, what its load cell reads, N m: at rest, minus gravity.
        g = self._gravity()
        self.load = [-g[0], -g[1], -g[2]]
        start = [self._encoder(i) for i in range(3)]
        self._samples = [deque([s] * ENCODER_AVERAGE, ENCODER_AVERAGE) for s in start]
        self._strain = [deque([self._adc(i)] * STRAIN_AVERAGE, STRAIN_AVERAGE) for i in range(3)]
        self.setpoint = [float(s) for s in start]  # ticks
        self.gains = [[0.005, 0.0, 0.0] for _ in range(3)]  # kp, ki, kd (firmware units)
        self.enabled = [True, True, True]
        self._integral = [0.0, 0.0, 0.0]  # ticks: the error's running mean (INTEGRAL_SIZE)
        self._last_error = [0.0, 0.0, 0.0]  # ticks (the firmware's PreviousError)
        self._converging = True  # the running means may still change at rest (`_skip_cycle`)
        self.velocity_ticks_s = [0.0, 0.0, 0.0]
        self._vel_ref: list[float] = list(start)
        self._vel_count = 0
        self.claw = 0.0
        self.claw_setpoint = 0.0
        self._t: float | None = None
        self.cycles = 0
        #: `_inputs()` when the last cycle changed nothing (None while anything moves).
        self._rest: tuple[object, ...] | None = None

    # --- SimDevice --------------------------------------------------------------------

    def receive(self, data: bytes, now: float) -> list[tuple[float, bytes]]:
        """Handle one host packet at time `now` (s); silence for anything the firmware drops."""
        self.advance(now)
        if len(data) != PACKET_SIZE:
            return []
        try:
            cmd = decode_command(data)
        except DecodeError:
            return []
        if isinstance(cmd, Status) and self.firmware == "stock_silent":
            return []
        reply = self._handle(cmd, bytes(data))
        return [] if reply is None else [(REPLY_DELAY_S, reply)]

    def advance(self, now: float) -> None:
        """Run whole 2.5 ms PID cycles up to `now` (s); a gap over MAX_CATCHUP_S is cut."""
        if self._t is None:
            self._t = now
            return
        if now - self._t > MAX_CATCHUP_S:
            self._t = now - MAX_CATCHUP_S
        while self._t + CYCLE_S <= now + 1e-12:
            if self._rest is not None and self._rest == self._inputs():
                self._skip_cycle()  # at rest: a cycle would change nothing but the counters
            else:
                before = self._state() if self._still() else None
                self._cycle()
                self._converging = True
                still = before is not None and self._still() and self._state() == before
                self._rest = self._inputs() if still else None
            self._t += CYCLE_S

    # --- at rest: the same bytes without the arithmetic --------------------------------

    def _inputs(self) -> tuple[object, ...]:
        """Everything a cycle reads that a command or a test may change."""
        return (self.q[:], self.qd[:], self.setpoint[:], [g[:] for g in self.gains],
                self.enabled[:], self.claw, self.claw_setpoint, self.m_tip)

    def _state(self) -> tuple[object, ...]:
        """Everything a cycle writes, but its counters and the controller's running mean of
        the error: at rest that mean goes on converging to the (constant) error, and
        `_skip_cycle` goes on with it; it moves the output only where ki is not 0, and then
        the torque shows it."""
        return (self.q[:], self.qd[:], self.torque[:], self.load[:],
                [tuple(d) for d in self._samples],
                [tuple(d) for d in self._strain], self._last_error[:], self.claw)

    def _still(self) -> bool:
        """No joint moving and the velocity estimate already the zero it would compute."""
        return (not any(self.qd) and list(self.position_ticks) == self._vel_ref
                and all(v == 0.0 and math.copysign(1.0, v) > 0 for v in self.velocity_ticks_s))

    def _skip_cycle(self) -> None:
        """What `_cycle` does to a state it leaves unchanged: count, and take each enabled
        joint's running mean of the error one cycle on (`_pid`'s arithmetic; at rest the
        error is the last cycle's), until it no longer changes."""
        if self._converging:
            self._converging = False
            for i in range(3):
                if self.enabled[i]:
                    mean = self._mean_with(i, self._last_error[i])
                    if mean != self._integral[i]:
                        self._integral[i] = mean
                        self._converging = True
        self._vel_count += 1
        if self._vel_count >= VELOCITY_CYCLES:
            self._vel_count = 0
        self.cycles += 1

    # --- readings ---------------------------------------------------------------------

    @property
    def position_ticks(self) -> tuple[float, float, float]:
        """What GetPIDPosition returns: the 4-sample average of whole-tick encoder reads."""
        p = [sum(s) / ENCODER_AVERAGE for s in self._samples]
        return (p[0], p[1], p[2])

    @property
    def strain_adc(self) -> tuple[float, float, float]:
        a = [sum(s) / STRAIN_AVERAGE for s in self._strain]
        return (a[0], a[1], a[2])

    def _encoder(self, i: int) -> int:
        return round(self.offset[i] + self.sign[i] * self.q[i] * self.tpr[i] / (2 * math.pi))

    def _adc(self, i: int) -> float:
        v = self.adc_offset[i] + self.load[i] / self.adc_scale[i]
        return round(min(1.0, max(0.0, v)) * ADC_STEPS) / ADC_STEPS

    # --- commands ---------------------------------------------------------------------

    def _handle(self, cmd: SetPid | Status | SetGain | SetClaw,
                request: bytes) -> bytes | None:
        if isinstance(cmd, SetPid):
            for i, sp in enumerate(cmd.setpoints):
                if abs(sp.position_ticks - self.setpoint[i]) > SETPOINT_DEADBAND_TICKS:
                    self.setpoint[i] = sp.position_ticks
                    self.enabled[i] = True
                    # a new setpoint starts the controller afresh (PidServer's SetPIDTimed:
                    # `InitAbsPIDWithPosition` zeroes integralTotal and PreviousError)
                    self._integral[i] = self._last_error[i] = 0.0
            reading = (self.position_ticks, self._velocity(), self.strain_adc)
            return encode_reply(SetPidReply(*reading), request, echo=self.echo)
        if isinstance(cmd, Status):
            if self.firmware == "stock_99":  # SimplePacketComs: no server for the id
                return ERROR_REPLY.pack(ERROR_ID, int(cmd.command_id)) + bytes(PACKET_SIZE - 8)
            reading = (self.position_ticks, self._velocity(), self.strain_adc)
            return encode_reply(StatusReply(*reading), request, echo=self.echo)
        if isinstance(cmd, SetGain):
            i = cmd.axis
            # the controller's history (its running mean, the last error) is kept: PID_Bowler's
            # setPIDConstants sets the gains only
            self.enabled[i] = False
            self.gains[i] = [cmd.kp, cmd.ki, cmd.kd]
            self.enabled[i] = True
            return self._ack(cmd.command_id, request)
        self.claw_setpoint = cmd.value
        return self._ack(cmd.command_id, request)

    def _ack(self, command_id: int, request: bytes) -> bytes | None:
        """SET_GAIN's and SET_CLAW's reply, as the build answers them (module doc)."""
        how = self.gain_claw_reply
        if how == "silent":
            return None
        if how == "other":  # e.g. a build that leaves its own values in the buffer
            return encode_packet(command_id, [1.0, 2.0, 3.0, 0.5])
        return encode_reply(Ack(command_id), request, echo=self.echo or how == "echo")

    def _velocity(self) -> tuple[float, float, float]:
        v = self.velocity_ticks_s
        return (v[0], v[1], v[2])

    # --- one 2.5 ms cycle -------------------------------------------------------------

    def _cycle(self) -> None:
        dt = CYCLE_S
        measured = self.position_ticks
        gravity = self._gravity()
        inertia = self._inertia()
        for i in range(3):
            u = self._pid(i, measured[i]) if self.enabled[i] else 0.0
            # Motor: voltage fraction u/span, torque falls with speed (back-EMF).
            drive = self.stall_torque * u / OUTPUT_SPAN * self.sign[i]
            damping = self.stall_torque / self.free_speed + self.viscous
            self.torque[i] = drive - self.stall_torque / self.free_speed * self.qd[i]
            push = drive + gravity[i]
            w = self.qd[i]
            if w == 0.0 and abs(push) <= self.coulomb:
                self.load[i] = -gravity[i]
                continue  # static friction holds
            friction = self.coulomb * math.copysign(1.0, w if w != 0.0 else push)
            # Semi-implicit: the speed-proportional terms are integrated implicitly (stable).
            w_new = (w + dt * (push - friction) / inertia[i]) / (1.0 + dt * damping / inertia[i])
            if w != 0.0 and w_new * w < 0.0:
                w_new = 0.0  # Coulomb friction stops, never reverses, the joint within a step
            self.qd[i] = w_new
            # the link's own inertia (the reflected inertia is the motor side's) times its
            # acceleration, and the weight it holds
            link_inertia = inertia[i] - self.reflected_inertia
            self.load[i] = link_inertia * (w_new - w) / dt - gravity[i]
            self.q[i] += w_new * dt
            lo, hi = self.hard_stops[i]
            if not lo <= self.q[i] <= hi:  # the mechanism's end stop: the joint stops dead
                self.q[i] = min(hi, max(lo, self.q[i]))
                self.qd[i] = 0.0
                self.load[i] = -gravity[i]
        for i in range(3):
            self._samples[i].append(self._encoder(i))
            self._strain[i].append(self._adc(i))
        self._update_velocity()
        step = self.claw_rate * dt
        self.claw += max(-step, min(step, self.claw_setpoint - self.claw))
        self.cycles += 1

    def _pid(self, i: int, measured: float) -> float:
        """One cycle of the firmware's controller (PID_Bowler `RunAbstractPIDCalc`): the
        derivative is the error's change over the cycle (not per second), the integral the
        error's running mean (`INTEGRAL_SIZE`), zeroed as the error changes sign; the
        output clamped as `setOutput` clamps it."""
        kp, ki, kd = self.gains[i]
        error = self.setpoint[i] - measured
        last = self._last_error[i]
        integral = self._mean_with(i, error)
        if (last >= 0.0 and error < 0.0) or (last < 0.0 and error >= 0.0):
            integral = 0.0
        self._integral[i] = integral
        self._last_error[i] = error
        u = kp * error + kd * (error - last) + ki * integral
        return max(-OUTPUT_SPAN, min(OUTPUT_SPAN, u))

    def _mean_with(self, i: int, error: float) -> float:
        """Joint `i`'s running mean of the error taken one cycle on with `error` (the
        firmware's `integralTotal`; the one expression for a cycle run or skipped)."""
        return error / INTEGRAL_SIZE + self._integral[i] * (INTEGRAL_SIZE - 1.0) / INTEGRAL_SIZE

    def _update_velocity(self) -> None:
        self._vel_count += 1
        if self._vel_count < VELOCITY_CYCLES:
            return
        now = self.position_ticks
        span = VELOCITY_CYCLES * CYCLE_S
        self.velocity_ticks_s = [(now[i] - self._vel_ref[i]) / span for i in range(3)]
        self._vel_ref = list(now)
        self._vel_count = 0

    def _gravity(self) -> list[float]:
        """Gravity torque on each joint (N m, positive drives the joint positive)."""
        q1, q2 = self.q[1], self.q[2]
        upper = (self.m2 * self.l2 / 2 + (self.m3 + self.m_tip) * self.l2) * math.cos(q1)
        forearm = (self.m3 * self.l3 / 2 + self.m_tip * self.l3) * math.sin(q1 - q2)
        return [0.0, -GRAVITY * (upper + forearm), GRAVITY * forearm]

    def _inertia(self) -> list[float]:
        """Diagonal joint inertia (kg m^2) at the present pose; coupling terms ignored."""
        q1, q2 = self.q[1], self.q[2]
        ex, ez = self.l2 * math.cos(q1), self.l2 * math.sin(q1)  # elbow, from the shoulder
        dx, dz = math.sin(q1 - q2), -math.cos(q1 - q2)  # forearm direction
        cx, cz = ex + self.l3 / 2 * dx, ez + self.l3 / 2 * dz  # forearm centre of mass
        tx, tz = ex + self.l3 * dx, ez + self.l3 * dz  # tip
        m2, m3, mt, l2, l3 = self.m2, self.m3, self.m_tip, self.l2, self.l3
        base = m2 * (ex / 2) ** 2 + m3 * cx**2 + mt * tx**2
        shoulder = m2 * l2**2 / 3 + m3 * (cx**2 + cz**2 + l3**2 / 12) + mt * (tx**2 + tz**2)
        elbow = m3 * l3**2 / 3 + mt * l3**2
        r = self.reflected_inertia
        return [r + base, r + shoulder, r + elbow]
