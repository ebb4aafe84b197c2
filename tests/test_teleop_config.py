"""`[[teleop]]` tables (app/teleop/config.py): a pair's defaults applied to a session and a
request's own fields winning, and the tables refused at start with the reason."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _wait import wait_for

from app.arms.loading import load_arms
from app.config.profiles import ConfigError
from app.service import ArmService
from app.teleop.config import load_teleop
from tests.conftest import make_settings, running_client

API = "/api/v1"
EXAMPLE = Path(__file__).resolve().parents[1] / "config" / "teleop_omx.toml"
ARMS = """
[[arms]]
profile = "openmanipulator_x"
name = "leader"

[[arms]]
profile = "openmanipulator_x"
name = "follower"
"""


def write(tmp_path: Path, tables: str) -> Path:
    p = tmp_path / "teleop.toml"
    # a bare key goes before the first table (TOML puts it in the table above otherwise)
    p.write_text(ARMS + tables if tables.startswith("[[") else tables + ARMS)
    return p


def test_the_example_config_loads() -> None:
    pairs = load_teleop(EXAMPLE, load_arms(EXAMPLE))
    assert [(p.leader, p.follower, p.clamp_margin) for p in pairs] == [
        ("leader", "follower", 0.05)]


async def test_a_pairs_offset_and_clamp_apply_and_a_request_wins(tmp_path: Path) -> None:
    cfg = write(tmp_path, """
[[teleop]]
leader = "leader"
follower = "follower"
rate_hz = 40
offset = [0.2, 0.0, 0.0, 0.0]
clamp_margin = 0.1
""")
    async with running_client(make_settings(config=str(cfg))) as (app, c):
        leader: ArmService = app.state.services["leader"]
        follower: ArmService = app.state.services["follower"]
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower"})
        assert r.status_code == 201 and r.json()["rate_hz"] == 40, r.text
        sid = r.json()["id"]
        goal = [0.5, -0.4, 0.3, 0.6]
        r = await c.post(f"{API}/arms/leader/move/joints", json={"positions": goal,
                                                                 "wait": True})
        assert r.status_code == 200, r.text
        want = np.array(goal) + [0.2, 0.0, 0.0, 0.0]
        await wait_for(lambda: np.allclose(follower.positions, want, atol=0.003),
                       what="the follower at the leader's joints plus the waist offset")
        # the waist's target beyond its limit less the margin is clamped there
        top = float(follower.model.upper[0]) - 0.1
        r = await c.post(f"{API}/arms/leader/move/joints",
                         json={"positions": [top - 0.1, -0.4, 0.3, 0.6], "wait": True})
        assert r.status_code == 200, r.text
        await wait_for(lambda: abs(follower.positions[0] - top) < 0.003,
                       what="the follower's waist clamped 0.1 rad inside its limit")
        assert leader.positions is not None
        assert (await c.delete(f"{API}/teleop/{sid}")).status_code == 200
        # the request's own fields win over the table's
        r = await c.post(f"{API}/teleop", json={"leader": "leader", "follower": "follower",
                                                "rate_hz": 60, "offset": [0, 0, 0, 0]})
        assert r.status_code == 201 and r.json()["rate_hz"] == 60, r.text
        await wait_for(lambda: np.allclose(follower.positions, leader.positions, atol=0.003),
                       what="the follower on the leader, no offset")
        assert (await c.delete(f"{API}/teleop/{r.json()['id']}")).status_code == 200


@pytest.mark.parametrize(("tables", "says"), [
    ('[[teleop]]\nleader = "leader"\nfollower = "follower"\nscael = [1.0]\n', "scael"),
    ('[[teleop]]\nleader = "leader"\nfollower = "nope"\n', "follower = 'nope'"),
    ('[[teleop]]\nleader = "leader"\nfollower = "leader"\n', "both"),
    ('[[teleop]]\nleader = "leader"\nfollower = "follower"\nrate_hz = 200\n', "rate_hz"),
    ('[[teleop]]\nleader = "leader"\nfollower = "follower"\n'
     '[[teleop]]\nleader = "leader"\nfollower = "follower"\n', "one [[teleop]] table"),
    ('teleop = 3\n', "[[teleop]] tables"),
])
def test_bad_tables_are_refused_at_start(tmp_path: Path, tables: str, says: str) -> None:
    cfg = write(tmp_path, tables)
    with pytest.raises(ConfigError) as err:
        load_teleop(cfg, load_arms(cfg))
    assert says in str(err.value)
