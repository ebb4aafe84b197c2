"""Shared bits of the example scripts: the `--url`/`--token` options and a timestamped log."""

from __future__ import annotations

import argparse
import os
import sys
import time

_T0 = time.monotonic()


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--url", default=os.environ.get("ARMSERVER_URL", "http://127.0.0.1:8000"),
                   help="server base URL (env ARMSERVER_URL; default %(default)s)")
    p.add_argument("--token", default=os.environ.get("ARMSERVER_TOKEN"),
                   help="bearer token (env ARMSERVER_TOKEN)")
    return p


def log(*parts: object) -> None:
    """One line on stdout, prefixed with seconds since the script started."""
    print(f"[{time.monotonic() - _T0:7.2f}s]", *parts, flush=True)


def fmt(v: object) -> str:
    """A tip (Vec3) or a joint vector, compactly, in mm for tips and rad/m for joints."""
    if hasattr(v, "x"):
        x, y, z = (getattr(v, k) * 1000 for k in ("x", "y", "z"))
        return f"({x:+7.1f}, {y:+7.1f}, {z:+7.1f}) mm"
    return "[" + ", ".join(f"{float(x):+.3f}" for x in v) + "]"  # type: ignore[attr-defined]


def dist(a: object, b: object) -> float:
    """Distance between two tips (Vec3 or (x, y, z)), m."""
    def xyz(p: object) -> tuple[float, float, float]:
        if hasattr(p, "x"):
            return (p.x, p.y, p.z)  # type: ignore[attr-defined]
        return tuple(p)  # type: ignore[arg-type,return-value]
    pa, pb = xyz(a), xyz(b)
    return sum((u - v) ** 2 for u, v in zip(pa, pb, strict=True)) ** 0.5


def fail(msg: str) -> None:
    log("FAIL:", msg)
    sys.exit(1)
