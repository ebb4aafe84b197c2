"""Batch (numpy) vs point-by-point (Python loop with math) FK and IK throughput.

Run: ``python bench/kinematics.py``. Prints points/s for both arms and the
speedup of the vectorised code; no asserts (figures depend on the machine).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from kinematics import pprp, rrr  # noqa: E402

N_BATCH = 100_000
N_LOOP = 2_000
G3 = rrr.RRR()
G4 = pprp.PPRP()


def rrr_fk_point(q: Sequence[float]) -> tuple[float, float, float]:
    q0, q1, q2 = q
    rho = G3.l2 * math.cos(q1) + G3.l3 * math.sin(q1 - q2)
    z = G3.l1 + G3.l2 * math.sin(q1) - G3.l3 * math.cos(q1 - q2)
    return math.cos(q0) * rho, math.sin(q0) * rho, z


def rrr_ik_point(p: Sequence[float]) -> list[tuple[float, float, float]]:
    """All four branches, as rrr.ik does."""
    x, y, z = p
    zr, rho, q0 = z - G3.l1, math.hypot(x, y), math.atan2(y, x)
    c = (rho * rho + zr * zr - G3.l2**2 - G3.l3**2) / (2 * G3.l2 * G3.l3)
    t2 = math.acos(max(-1.0, min(1.0, c)))
    out = []
    for base, reach in ((q0, rho), (q0 + math.pi, -rho)):
        for e in (t2, -t2):
            elbow = math.atan2(G3.l3 * math.sin(e), G3.l2 + G3.l3 * math.cos(e))
            t1 = math.atan2(zr, reach) - elbow
            out.append((base, t1, -e - math.pi / 2))
    return out


def pprp_fk_point(q: Sequence[float]) -> tuple[float, float, float]:
    dx, dy, t3, dz = q
    return dx - G4.r * math.sin(t3), dy + G4.r * math.cos(t3), dz - G4.h


def _mat4(a: list[list[float]], b: list[list[float]]) -> list[list[float]]:
    return [[sum(a[i][k] * b[k][j] for k in range(4)) for j in range(4)] for i in range(4)]


def _dh(th: float, d: float, a: float, al: float) -> list[list[float]]:
    ct, st, ca, sa = math.cos(th), math.sin(th), math.cos(al), math.sin(al)
    return [[ct, -st * ca, st * sa, a * ct], [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d], [0.0, 0.0, 0.0, 1.0]]


_T0 = [[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]


def pprp_fk_dh_point(q: Sequence[float]) -> tuple[float, float, float]:
    """The same DH product as pprp.fk, one point at a time."""
    dx, dy, t3, dz = q
    hp = math.pi / 2
    t = _T0
    for row in (_dh(0.0, dx, 0.0, -hp), _dh(-hp, dy, 0.0, hp), _dh(t3 + hp, 0.0, G4.r, 0.0),
                _dh(0.0, dz - G4.h, 0.0, 0.0)):
        t = _mat4(t, row)
    return t[0][3], t[1][3], t[2][3]


def pprp_fk_closed(q: np.ndarray) -> np.ndarray:
    return np.stack([q[:, 0] - G4.r * np.sin(q[:, 2]), q[:, 1] + G4.r * np.cos(q[:, 2]),
                     q[:, 3] - G4.h], axis=-1)


def pprp_ik_point(p: Sequence[float]) -> list[tuple[float, float, float, float]]:
    x, y, z = p
    a = math.asin(-x / G4.r)
    return [(0.0, y - G4.r * math.cos(t), t, z + G4.h) for t in (a, math.pi - a)]


def rate(fn: Callable[[], object], n: int, repeat: int = 3) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def main() -> None:
    rng = np.random.default_rng(0)
    q3 = rng.uniform([-1.57, -0.35, -1.2], [1.57, 1.75, 2.4], size=(N_BATCH, 3))
    q4 = rng.uniform([0.0, -0.075, -1.5, 0.0], [0.0, 0.075, 1.5, 0.14], size=(N_BATCH, 4))
    p3, p4 = rrr.fk(q3, G3), pprp.fk(q4, G4)
    l3, l4 = q3[:N_LOOP].tolist(), q4[:N_LOOP].tolist()
    m3, m4 = p3[:N_LOOP].tolist(), p4[:N_LOOP].tolist()
    rows = [
        ("rrr", "fk", rate(lambda: rrr.fk(q3, G3), N_BATCH),
         rate(lambda: [rrr_fk_point(q) for q in l3], N_LOOP)),
        ("rrr", "ik (4 branches)", rate(lambda: rrr.ik(p3, G3), N_BATCH),
         rate(lambda: [rrr_ik_point(p) for p in m3], N_LOOP)),
        ("rrr", "jacobian", rate(lambda: rrr.jacobian(q3, G3), N_BATCH), float("nan")),
        ("pprp", "fk (DH product)", rate(lambda: pprp.fk(q4, G4), N_BATCH),
         rate(lambda: [pprp_fk_dh_point(q) for q in l4], N_LOOP)),
        ("pprp", "fk (closed form)", rate(lambda: pprp_fk_closed(q4), N_BATCH),
         rate(lambda: [pprp_fk_point(q) for q in l4], N_LOOP)),
        ("pprp", "ik (dx_zero, 2)", rate(lambda: pprp.ik(p4, G4), N_BATCH),
         rate(lambda: [pprp_ik_point(p) for p in m4], N_LOOP)),
    ]
    print(f"batch: {N_BATCH} points with numpy; loop: {N_LOOP} points with math, one at a time")
    print(f"{'arm':<5} {'op':<17} {'batch pts/s':>14} {'loop pts/s':>13} {'speedup':>8}")
    for arm, op, b, lp in rows:
        sp = f"{b / lp:7.1f}x" if lp == lp else "      -"
        lps = f"{lp:13,.0f}" if lp == lp else f"{'-':>13}"
        print(f"{arm:<5} {op:<17} {b:14,.0f} {lps} {sp}")


if __name__ == "__main__":
    main()
