"""The arm-type registry (issue 13): one package per arm type, a core that names none.

- the core (app/ minus app/arms/) has no switch on an arm type, and the dashboard neither;
- the registry: lazy lookup, a clear error for an unknown name, the built-in profiles;
- each model's joint chain (what the dashboard draws) equals its joint origins (what the
  envelope checks), in Python and in the dashboard's own JavaScript;
- wrist pitch on arms without a wrist: absent from reports, 422 when asked for.
"""

from __future__ import annotations

import io
import json
import re
import subprocess
import tokenize
from pathlib import Path

import httpx
import numpy as np
import pytest
from _deps import NODE, missing_message
from fastapi import FastAPI

from app import arms
from app.arms import ARM_TYPES, arm_routers, arm_type, builtin_profiles
from app.arms.loading import check_profile, load_arms, load_profile
from app.arms.model import chain_points
from app.config import ConfigError
from kinematics import rrr

ROOT = Path(__file__).resolve().parents[1]
API = "/api/v1"

#: Names that switch on an arm type: its name, its kinematics module, the old `is_rrr`.
_TYPE_NAME = re.compile(r"(?i)rbe3001|angler|openmanipulator|is_rrr|pprp|^rrr$|^omx$")
#: Where an arm type's name may stand in the core all the same, and why.
_ALLOWED_FILES = (
    # what every simulator shares stays in app/sim (each arm type's simulator is in its package)
    "app/sim/",
    # the client mirrors the route paths (`/arms/{arm}/rbe3001/...` -> `rbe3001_status`);
    # it is the `client` branch's and calls the server, never switches on a type
    "app/client",
)
_ALLOWED_NAMES = {
    # the RBE3001 pass-through's wire schema in app/schemas/passthrough.py (the client's)
    "Rbe3001Status",
}


def type_switches(source: str, types: set[str]) -> list[str]:
    """Identifiers naming an arm type or its maths, and string literals equal to an arm
    type's name (`profile.model == "rbe3001"`), in Python source; comments and docstrings
    are free to name them."""
    found = []
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.NAME and _TYPE_NAME.search(tok.string) \
                and tok.string not in _ALLOWED_NAMES:
            found.append(f"{tok.start[0]}: {tok.string}")
        elif tok.type == tokenize.STRING:
            value = re.sub(r"^[rbfuRBFU]*(['\"]{1,3})(.*)\1$", r"\2", tok.string, flags=re.S)
            if value.lower() in types:
                found.append(f"{tok.start[0]}: {tok.string}")
    return found


def js_type_switches(source: str, types: set[str]) -> list[str]:
    return [m.group(0) for m in re.finditer(r"([\"'`])([a-z0-9_]+)\1", source)
            if m.group(2) in types]


def test_the_scanner_finds_a_type_switch() -> None:
    types = set(ARM_TYPES)
    assert type_switches('if profile.model == "rbe3001":\n    pass\n', types)
    assert type_switches("x = m.is_rrr\n", types)
    assert type_switches("from kinematics import pprp\n", types)
    assert not type_switches('"""The rbe3001 and the angler are documented here."""\n', types)
    assert js_type_switches('if (detail.model === "angler") {}', types)
    assert not js_type_switches("// the rbe3001's base", types)


def test_the_core_names_no_arm_type() -> None:
    types = set(ARM_TYPES) | {"rrr", "pprp"}
    hits = []
    for path in sorted((ROOT / "app").rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        if rel.startswith("app/arms/") or rel.startswith(_ALLOWED_FILES):
            continue
        hits += [f"{rel}:{h}" for h in type_switches(path.read_text(encoding="utf-8"), types)]
    for path in sorted((ROOT / "app" / "web" / "static").glob("*.js")):
        rel = path.relative_to(ROOT).as_posix()
        hits += [f"{rel}: {h}" for h in js_type_switches(path.read_text(encoding="utf-8"), types)]
    assert hits == [], "the core switches on an arm type:\n" + "\n".join(hits)


# ------------------------------------------------------------------ registry


def test_unknown_arm_type_names_the_known_ones(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"unknown arm type 'scara'.*\"angler\",.*\"rbe3001\""):
        arm_type("scara")
    text = builtin_profiles()["rbe3001"].read_text(encoding="utf-8")
    assert '\nmodel = "rbe3001"' in text
    path = tmp_path / "scara.toml"
    path.write_text(text.replace('\nmodel = "rbe3001"', '\nmodel = "scara"'), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"model: .*unknown arm type 'scara'.*\"angler\""):
        load_profile(path)


def test_the_registry_loads_a_package_on_first_use_only(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(arms, "_LOADED", {})
    assert arm_type("angler") is arm_type("angler")
    assert set(arms._LOADED) == {"angler"}


@pytest.mark.parametrize("name", sorted(ARM_TYPES))
def test_each_builtin_profile_is_valid_for_its_type(name: str) -> None:
    shipped = builtin_profiles()
    assert shipped[name].parent.name == name  # inside its own package
    assert shipped[name].parent == ROOT / "app" / "arms" / name
    p = load_profile(name)
    t = arm_type(p.model)
    model = t.model(p)
    assert t.name == p.model == name
    assert model.n == t.joints == len(p.joints)
    assert t.geometry_keys <= set(p.geometry)
    assert t.has_pitch == model.has_pitch
    q = (model.lower + model.upper) / 2
    assert np.allclose(model.joint_origins(q)[-1], model.fk(q), atol=1e-12)
    assert len(model.points) == model.joint_origins(q).shape[-2]
    bad = p.model_dump()
    bad["joints"] = bad["joints"][:-1]
    with pytest.raises(ValueError, match=f"{name} has {t.joints} joints, profile gives"):
        check_profile(bad)


def test_the_default_server_hosts_every_builtin_profile() -> None:
    # except those of a type that says default_server=False (API.md: rbe3001 and angler)
    assert [p.name for p in load_arms(None)] == [
        n for n in builtin_profiles() if arm_type(load_profile(n).model).default_server]
    assert {"rbe3001", "angler"} <= set(builtin_profiles())


def test_each_router_is_mounted_once() -> None:
    routers = arm_routers()
    assert len({id(r) for r in routers}) == len(routers)
    prefixes = sorted(r.prefix for r in routers)
    assert prefixes == ["/arms/{arm}/dynamixel", "/arms/{arm}/rbe3001"]


def test_the_shared_workspace_box_is_the_rrr_one() -> None:
    """The base class's sampled box replaced kinematics.rrr.bounds for the rbe3001: the same
    samples, the same box."""
    model = arm_type("rbe3001").model(load_profile("rbe3001"))
    lo, hi = rrr.bounds(model.geom, model.lower, model.upper,  # type: ignore[attr-defined]
                        rng=np.random.default_rng(0))
    assert np.array_equal(model.bounds()[0], lo) and np.array_equal(model.bounds()[1], hi)


# ------------------------------------------------------------------ the chain


def _random_q(name: str, k: int) -> tuple[object, np.ndarray]:
    model = arm_type(name).model(load_profile(name))
    rng = np.random.default_rng(7)
    return model, rng.uniform(model.lower, model.upper, size=(k, model.n))


@pytest.mark.parametrize("name", sorted(ARM_TYPES))
def test_the_chain_draws_the_joint_origins(name: str) -> None:
    model, qs = _random_q(name, 50)
    for q in qs:
        assert np.allclose(chain_points(model.chain(), q),  # type: ignore[attr-defined]
                           model.joint_origins(q), atol=1e-12)  # type: ignore[attr-defined]


@pytest.mark.skipif(NODE is None, reason=missing_message("node"))
@pytest.mark.parametrize("name", sorted(ARM_TYPES))
def test_the_dashboard_draws_the_joint_origins(name: str) -> None:
    """app/web/static/app.js's own chainPoints, run by node on the described chain."""
    src = (ROOT / "app" / "web" / "static" / "app.js").read_text(encoding="utf-8")
    start, end = src.index("function rotation("), src.index("function bounds(")
    model, qs = _random_q(name, 10)
    chain = model.describe()  # type: ignore[attr-defined]
    script = src[start:end] + (f"\nconst ch = {json.dumps(chain)};\n"
                               f"const qs = {json.dumps(qs.tolist())};\n"
                               "console.log(JSON.stringify(qs.map((q) => chainPoints(ch, q))));\n")
    assert NODE is not None
    out = subprocess.run([NODE, "-e", script], capture_output=True, text=True, timeout=60,
                         check=True)
    got = np.array(json.loads(out.stdout))
    want = model.joint_origins(qs)  # type: ignore[attr-defined]
    assert got.shape == want.shape
    assert np.allclose(got, want, atol=1e-12)


# ------------------------------------------------------------------ API


async def test_arm_detail_describes_the_chain(app_client: httpx.AsyncClient) -> None:
    for name in ("rbe3001", "angler"):
        r = await app_client.get(f"{API}/arms/{name}")
        assert r.status_code == 200, r.text
        body = r.json()
        assert "pitch" not in body["capabilities"]  # unchanged for arms without a wrist
        assert body["capabilities"]["protocol"] == arm_type(name).protocol
        ch = body["chain"]
        assert ch["points"][0] == "base" and ch["points"][-1] == "tip"
        assert sum(st["point"] is not None for st in ch["steps"]) == len(ch["points"]) - 1


async def test_pitch_on_an_arm_without_a_wrist(
        app_and_client: tuple[FastAPI, httpx.AsyncClient]) -> None:
    app, client = app_and_client
    r = await client.post(f"{API}/arms/rbe3001/kinematics/forward",
                          json={"positions": [0.1, 0.5, -0.3]})
    assert r.status_code == 200 and "pitch" not in r.json()["tip"]
    state = (await client.get(f"{API}/arms/rbe3001/state")).json()
    assert "pitch" not in state["tip"]
    # without a pitch the point is reachable; with one it cannot be met: 422, nothing moves
    p = {"x": 0.2, "y": 0.05, "z": 0.15}
    assert (await client.post(f"{API}/arms/rbe3001/kinematics/inverse", json=p)).status_code \
        == 200
    r = await client.post(f"{API}/arms/rbe3001/kinematics/inverse", json={**p, "pitch": 0.0})
    assert r.status_code == 422 and r.json()["code"] == "unreachable", r.text
    assert "no wrist" in r.json()["detail"]
    r = await client.post(f"{API}/arms/angler/move/pose",
                          json={"x": 0.05, "y": 0.1, "z": 0.0, "pitch": 0.3})
    assert r.status_code == 422 and r.json()["code"] == "unreachable", r.text
    svc = app.state.services["angler"]
    assert svc.motion.current is None and not list(svc.motion._queue)
