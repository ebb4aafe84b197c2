"""Workspace of each arm: tip positions reachable within the joint limits, side and top views.

Offline by default (the arm model from the built-in profiles: `app.arms.model_for`);
with `--url` it asks a running server's `GET /workspace` instead, so the plot shows what that
server's profiles allow. Writes docs/workspace_<arm>.png.

    python examples/workspace_plot.py                      # both arms, offline
    python examples/workspace_plot.py --url http://127.0.0.1:8000 --arms rbe3001
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _common import log  # noqa: E402

DOCS = Path(__file__).resolve().parent.parent / "docs"


def offline_points(arm: str, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """(points (n, 3) m, home tip (3,), joint-limit corners' tips, joint names) from the profile."""
    from app.arms import model_for
    from app.arms.loading import load_profile

    profile = load_profile(arm)
    model = model_for(profile)
    pts = model.workspace(n, seed=0)
    home = model.fk(np.asarray(profile.home or (model.lower + model.upper) / 2, dtype=float))
    return pts, home, model.lower, model.names


def server_points(url: str, token: str | None, arm: str, n: int) -> tuple[np.ndarray, np.ndarray]:
    from app.client import ArmClient

    with ArmClient(url, token=token) as c:
        ws = c.workspace(arm, n=n)
        home = c.state(arm).tip
    pts = np.array([[p.x, p.y, p.z] for p in ws.points])
    return pts, np.array([home.x, home.y, home.z])


def plot(arm: str, pts: np.ndarray, home: np.ndarray, out: Path, source: str) -> None:
    fig, (side, top) = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
    mm = pts * 1000.0
    rho = np.hypot(mm[:, 0], mm[:, 1]) if arm == "rbe3001" else mm[:, 0]
    side_label = "radial distance from the base axis, mm" if arm == "rbe3001" else "x, mm"
    side.scatter(rho, mm[:, 2], s=1.5, alpha=0.35, c=mm[:, 1], cmap="viridis", rasterized=True)
    h_side = np.hypot(home[0], home[1]) * 1000 if arm == "rbe3001" else home[0] * 1000
    side.plot(h_side, home[2] * 1000, "r*", ms=12, label="home")
    side.set_xlabel(side_label)
    side.set_ylabel("z, mm")
    side.set_title("side view (colour: y)")
    top.scatter(mm[:, 0], mm[:, 1], s=1.5, alpha=0.35, c=mm[:, 2], cmap="plasma", rasterized=True)
    top.plot(home[0] * 1000, home[1] * 1000, "r*", ms=12, label="home")
    top.plot(0, 0, "k+", ms=12, label="base origin")
    top.set_xlabel("x, mm")
    top.set_ylabel("y, mm")
    top.set_title("top view (colour: z)")
    for ax in (side, top):
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    lo, hi = pts.min(axis=0) * 1000, pts.max(axis=0) * 1000
    fig.suptitle(f"{arm} workspace: {len(pts)} tips from joints uniform within the limits "
                 f"({source})\nx {lo[0]:.0f}..{hi[0]:.0f}, y {lo[1]:.0f}..{hi[1]:.0f}, "
                 f"z {lo[2]:.0f}..{hi[2]:.0f} mm")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--url", default=None, help="ask this server's /workspace (default: offline)")
    p.add_argument("--token", default=os.environ.get("ARMSERVER_TOKEN"))
    p.add_argument("--arms", nargs="+", default=["rbe3001", "angler"])
    p.add_argument("--points", type=int, default=5000)
    p.add_argument("--out-dir", type=Path, default=DOCS)
    a = p.parse_args(argv)
    for arm in a.arms:
        if a.url:
            pts, home = server_points(a.url, a.token, arm, a.points)
            source = f"GET {a.url}/api/v1/arms/{arm}/workspace"
        else:
            pts, home, _, _ = offline_points(arm, a.points)
            source = "app.arms.model_for, built-in profile"
        out = a.out_dir / f"workspace_{arm}.png"
        plot(arm, pts, home, out, source)
        log(f"{arm}: {len(pts)} points, bounds {np.round(pts.min(0), 3).tolist()} .. "
            f"{np.round(pts.max(0), 3).tolist()} m -> {out}")
    log("workspace plots done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
