"""The client (app.client: the async client, the sync one made from it, the CLI) against a
real uvicorn server over the simulated arms: typed answers, the server's error codes as
exceptions, the lease keeper, telemetry iterators; and the retry policy against a scripted
transport."""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import httpx
import pytest
import uvicorn
from _serve import free_port
from _wait import wait_for, wait_until

from app import client as cl
from app import schemas as s
from app.client import ArmClient, AsyncArmClient
from app.client.cli import main as cli_main
from app.config import Settings
from app.web.factory import create_app
from tests._http import HTTP

OPERATOR = "client-test-operator"


class Server:
    """A real uvicorn server over the default simulated arms, in a thread."""

    def __init__(self, settings: Settings) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=self.port,
                                log_level="warning", lifespan="on")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="client-test-uvicorn",
                                       daemon=True)

    def __enter__(self) -> Server:
        self.thread.start()
        deadline = time.monotonic() + 20.0
        headers = {"Authorization": f"Bearer {OPERATOR}"}
        while time.monotonic() < deadline:
            try:
                ok = all(HTTP.get(f"{self.url}/api/v1/arms/{arm}/state", headers=headers,
                                  timeout=1.0).status_code == 200
                         for arm in ("rbe3001", "angler"))
                if ok:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise RuntimeError("the server did not start")

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10.0)
        assert not self.thread.is_alive(), "the server's thread outlived the test"


def settings(**over: Any) -> Settings:
    base: dict[str, Any] = {"config": None, "operator_tokens": "", "viewer_tokens": "",
                            "cors_origins": "", "lease_ttl_s": 1.0}
    base.update(over)
    return Settings(**base)


@pytest.fixture(scope="module")
def server() -> Iterator[Server]:
    with Server(settings()) as srv:
        yield srv


@pytest.fixture(scope="module")
def auth_server() -> Iterator[Server]:
    with Server(settings(operator_tokens=OPERATOR, viewer_tokens="client-test-viewer")) as srv:
        yield srv


@pytest.fixture
def client(server: Server) -> Iterator[ArmClient]:
    with ArmClient(server.url, timeout=30.0) as c:
        yield c
        c.release_estop("rbe3001")
        c.release_estop("angler")


# ---------------------------------------------------------------- typed answers


def test_reads_are_typed(client: ArmClient) -> None:
    health = client.health()
    assert isinstance(health, s.Health) and set(health.arms) == {"rbe3001", "angler"}
    arms = client.arms()
    assert [type(a) for a in arms] == [s.ArmSummary, s.ArmSummary]
    detail = client.arm("rbe3001")
    assert isinstance(detail, s.ArmDetail) and [j.name for j in detail.joints] == [
        "base", "shoulder", "elbow"]
    st = client.state("angler")
    assert isinstance(st, s.Sample) and len(st.positions) == 4
    fk = client.forward("rbe3001", [0.0, 0.6, 0.3])
    assert isinstance(fk, s.ForwardResult) and len(fk.jacobian) == 3
    ik = client.inverse("rbe3001", fk.tip.x, fk.tip.y, fk.tip.z)
    assert isinstance(ik, s.InverseResult)
    assert any(sol.within_limits and max(abs(a - b) for a, b in
                                         zip(sol.positions, [0.0, 0.6, 0.3], strict=True)) < 1e-6
               for sol in ik.solutions)
    ws = client.workspace("angler", n=50)
    assert isinstance(ws, s.Workspace) and len(ws.points) == 50


def test_plan_previews_without_moving(client: ArmClient) -> None:
    before = client.state("rbe3001").positions
    plan = client.plan_pose("rbe3001", 0.2, 0.05, 0.08, path="line")
    assert isinstance(plan, s.Motion) and plan.path == "line" and plan.planned_path
    plan_j = client.plan_joints("rbe3001", [0.1, 0.6, 0.3])
    assert plan_j.planned_duration > 0
    after = client.state("rbe3001").positions
    assert max(abs(a - b) for a, b in zip(before, after, strict=True)) < 0.01


def test_move_wait_cancel(client: ArmClient) -> None:
    done = client.move_joints("rbe3001", [0.0, 0.6, 0.3], wait=True)
    assert done.status == "done" and done.final_positions is not None
    m = client.move_pose("rbe3001", 0.2, -0.05, 0.08, duration=2.0)
    assert m.status in ("queued", "running")
    end = client.cancel_motion("rbe3001", m.id)
    assert end.status == "stopped"
    m = client.move_joints("rbe3001", [0.0, 0.6, 0.3])
    assert client.wait_motion("rbe3001", m.id, timeout=30).status == "done"
    assert client.motion("rbe3001", m.id).status == "done"


def test_gripper_and_passthrough(client: ArmClient) -> None:
    assert client.gripper("rbe3001", 0.5).value == 0.5
    assert isinstance(client.rbe3001_status("rbe3001"), s.Rbe3001Status)
    assert client.rbe3001_set_claw("rbe3001", 0.0).ok
    ping = client.dxl_ping("angler")
    assert sorted(d.id for d in ping.devices) == [1, 2, 3, 4]
    assert [d.id for d in client.dxl_ping("angler", 2).devices] == [2]
    reg = client.dxl_read_register("angler", 1, "torque_enable")
    assert isinstance(reg, s.RegisterValue) and reg.raw == 1
    led = client.dxl_write_register("angler", 1, "led", 1)
    assert led.raw == 1 and client.dxl_read_register("angler", 1, "led").raw == 1
    rd = client.dxl_sync_read("angler", "present_position", [1, 2, 3, 4])
    assert set(rd.values) == {1, 2, 3, 4}
    assert client.dxl_sync_write("angler", "led", {1: 0, 2: 0}).ok


# ---------------------------------------------------------------- errors as exceptions


def test_error_codes_raise_their_exceptions(client: ArmClient) -> None:
    cases: list[tuple[Any, type[cl.ArmServerError], str, int]] = [
        (lambda: client.state("nope"), cl.NotFound, "unknown_arm", 404),
        (lambda: client.move_pose("rbe3001", 2.0, 2.0, 2.0), cl.Unreachable, "unreachable", 422),
        (lambda: client.move_joints("rbe3001", [3.0, 0.6, 0.3]), cl.JointLimit, "joint_limit",
         422),
        (lambda: client.gripper("angler", 1.0), cl.NoGripper, "no_gripper", 409),
        (lambda: client.rbe3001_status("angler"), cl.NotSupported, "not_supported", 409),
        (lambda: client.motion("rbe3001", "m0-nothing"), cl.NotFound, "unknown_motion", 404),
        (lambda: client.move_joints("rbe3001", [0.0, 0.6]), cl.InvalidRequest,
         "invalid_request", 422),
    ]
    for call, exc_type, code, status in cases:
        with pytest.raises(exc_type) as info:
            call()
        assert (info.value.code, info.value.status) == (code, status), info.value
        assert info.value.detail


def test_estop_latched_refuses_moves(client: ArmClient) -> None:
    assert client.estop("rbe3001").estop is True
    try:
        with pytest.raises(cl.EstopLatched) as info:
            client.move_joints("rbe3001", [0.0, 0.6, 0.3])
        assert info.value.status == 409
        assert client.arm("rbe3001").estop is True
    finally:
        assert client.release_estop("rbe3001").estop is False


def test_client_side_validation_refuses_before_sending(client: ArmClient) -> None:
    with pytest.raises(ValueError):
        client.move_joints("rbe3001", [float("nan"), 0.6, 0.3])
    with pytest.raises(ValueError):
        client.gripper("rbe3001", 1.5)


def test_unreachable_server_is_connection_failed() -> None:
    with ArmClient(f"http://127.0.0.1:{free_port()}", timeout=2.0) as c:
        with pytest.raises(cl.ConnectionFailed) as info:
            c.health()
    assert info.value.status == 0 and info.value.code == "connection_failed"


def test_tokens(auth_server: Server) -> None:
    with ArmClient(auth_server.url) as anon:
        assert anon.health().auth is True
        with pytest.raises(cl.Unauthorized):
            anon.arms()
        with pytest.raises(cl.Unauthorized):
            next(iter(anon.telemetry("rbe3001")))
    with ArmClient(auth_server.url, token="client-test-viewer") as viewer:
        assert viewer.state("rbe3001")
        with pytest.raises(cl.Forbidden):
            viewer.move_joints("rbe3001", [0.0, 0.6, 0.3])
    with ArmClient(auth_server.url, token=OPERATOR) as op:
        sample = next(iter(op.telemetry("rbe3001", rate=50)))
        assert isinstance(sample, s.Sample)


# ---------------------------------------------------------------- lease


def test_hold_lease_heartbeats_and_gates_others(auth_server: Server) -> None:
    with ArmClient(auth_server.url, token=OPERATOR) as a, \
            ArmClient(auth_server.url, token=OPERATOR) as b:
        with a.hold_lease("angler", every=0.2) as keeper:
            assert a.leases["angler"] == keeper.id
            time.sleep(1.5)  # under test: longer than the 1 s ttl, only the heartbeat keeps it
            wait_until(lambda: keeper.renewals >= 3 or keeper.error, what="three renewals")
            assert keeper.renewals >= 3 and keeper.error is None
            assert a.move_joints("angler", [0.0, 0.0, 0.0, 0.05], wait=True).status == "done"
            with pytest.raises(cl.Leased) as info:
                b.move_joints("angler", [0.0, 0.0, 0.0, 0.05])
            assert info.value.status == 409
            with pytest.raises(cl.Leased):
                b.take_lease("angler")
        assert "angler" not in a.leases
        lease = b.take_lease("angler")
        assert isinstance(lease, s.Lease)
        assert b.renew_lease("angler", lease.id).id == lease.id
        assert b.release_lease("angler", lease.id) is None


async def test_async_hold_lease(auth_server: Server) -> None:
    async with AsyncArmClient(auth_server.url, token=OPERATOR) as c:
        async with c.hold_lease("rbe3001", every=0.2) as keeper:
            await asyncio.sleep(1.3)  # under test: longer than the 1 s ttl
            await wait_for(lambda: keeper.renewals >= 3 or keeper.error, what="three renewals")
            assert keeper.renewals >= 3 and keeper.error is None
            m = await c.plan_joints("rbe3001", [0.0, 0.6, 0.3])
            assert m.status == "queued"
        assert "rbe3001" not in c.leases


# ---------------------------------------------------------------- async client and telemetry


async def test_async_client_typed_and_errors(server: Server) -> None:
    async with AsyncArmClient(server.url, timeout=30.0) as c:
        assert isinstance(await c.health(), s.Health)
        assert isinstance(await c.state("rbe3001"), s.Sample)
        m = await c.move_pose("rbe3001", 0.2, 0.0, 0.1, wait=True)
        assert m.status == "done"
        with pytest.raises(cl.Unreachable):
            await c.move_pose("rbe3001", 1.0, 1.0, 1.0)
        with pytest.raises(cl.NotFound) as info:
            await c.arm("nope")
        assert info.value.code == "unknown_arm"


async def test_telemetry_yields_increasing_seq_and_events(server: Server) -> None:
    async with AsyncArmClient(server.url) as c:
        seqs: list[int] = []
        events: list[str] = []

        async def consume() -> None:
            async for item in c.telemetry("rbe3001", rate=20, events=True):
                if isinstance(item, s.EventMessage):
                    events.append(item.event)
                else:
                    seqs.append(item.seq)
                if len(seqs) > 200 and "estop_released" in events:
                    return

        task = asyncio.create_task(consume())
        # samples flowing: the socket is subscribed, and will see the events
        await wait_for(lambda: seqs or task.done(), what="the first telemetry")
        await c.estop("rbe3001")
        await c.release_estop("rbe3001")
        await asyncio.wait_for(task, 10.0)
    gaps = [(a, b) for a, b in zip(seqs, seqs[1:], strict=False) if b != a + 1]
    assert not gaps, f"gaps in seq: {gaps[:5]} of {len(seqs)} samples from {seqs[0]}"
    assert {"estop", "estop_released"} <= set(events)


async def test_telemetry_messages_batch_at_the_rate(server: Server) -> None:
    async with AsyncArmClient(server.url) as c:
        msgs = []
        t0 = time.monotonic()
        async for msg in c.telemetry_messages("angler", rate=10):
            if isinstance(msg, s.TelemetryMessage):
                msgs.append(msg)
            if len(msgs) == 6:
                break
        took = time.monotonic() - t0
    assert all(m.arm == "angler" and m.dropped == 0 for m in msgs)
    assert sum(len(m.samples) for m in msgs) > 6  # batched: several samples a message
    assert 0.2 < took < 3.0


async def test_telemetry_refusal_raises_the_code(server: Server) -> None:
    async with AsyncArmClient(server.url) as c:
        with pytest.raises(cl.NotFound) as info:
            async for _ in c.telemetry("nope"):
                pass
    assert (info.value.code, info.value.status) == ("unknown_arm", 404)


def test_sync_telemetry(client: ArmClient) -> None:
    it = client.telemetry("angler", rate=50)
    seqs = [next(it).seq for _ in range(30)]
    it.close()  # type: ignore[attr-defined]
    assert seqs == list(range(seqs[0], seqs[0] + 30))


def test_sync_telemetry_left_early_then_the_client_goes_on(client: ArmClient) -> None:
    got: list[s.Sample] = []
    for sample in client.telemetry("rbe3001", rate=50):
        assert isinstance(sample, s.Sample)
        got.append(sample)
        if len(got) == 5:
            break  # closes the WebSocket on the client's loop
    assert [x.seq for x in got] == list(range(got[0].seq, got[0].seq + 5))
    assert client.state("rbe3001").seq >= got[-1].seq


def test_sync_client_close_stops_its_loop_thread(server: Server) -> None:
    c = ArmClient(server.url)
    assert c.health().status == "ok" and c._thread.is_alive()
    c.close()
    c.close()  # idempotent
    assert not c._thread.is_alive()
    with pytest.raises(RuntimeError, match="closed"):
        c.health()


async def test_sync_client_works_inside_a_running_event_loop(server: Server) -> None:
    """Its loop is its own thread's: a script that happens to run under asyncio may use it."""
    with ArmClient(server.url) as c:
        assert c.arm("angler").name == "angler"
        with pytest.raises(cl.NotFound) as info:
            c.arm("no-such-arm")
    assert info.value.code == "unknown_arm" and info.value.status == 404


# ---------------------------------------------------------------- retry policy (scripted transport)


class Script:
    """A transport answering from a list: an exception to raise, or (status, body)."""

    def __init__(self, *steps: Any) -> None:
        self.steps = list(steps)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        step = self.steps.pop(0)
        if isinstance(step, Exception):
            raise step
        status, body = step
        return httpx.Response(status, json=body)


HEALTH = {"status": "ok", "arms": {}, "auth": False}
LINK_DOWN = {"detail": "link down", "code": "link_down"}


def test_safe_calls_retry_on_connect_error_and_link_down() -> None:
    script = Script(httpx.ConnectError("refused"), (503, LINK_DOWN), (200, HEALTH))
    with ArmClient("http://x", transport=httpx.MockTransport(script)) as c:
        assert c.health().status == "ok"
    assert len(script.requests) == 3


def test_retries_are_bounded() -> None:
    script = Script(*[httpx.ConnectError("refused")] * 5)
    with ArmClient("http://x", transport=httpx.MockTransport(script)) as c:
        with pytest.raises(cl.ConnectionFailed):
            c.health()
    assert len(script.requests) == cl.RETRIES + 1


def test_moves_are_never_retried() -> None:
    script = Script(httpx.ConnectError("refused"), (503, LINK_DOWN))
    with ArmClient("http://x", transport=httpx.MockTransport(script)) as c:
        with pytest.raises(cl.ConnectionFailed):
            c.move_joints("a", [0.0])
        with pytest.raises(cl.LinkDown) as info:
            c.move_pose("a", 0.1, 0.0, 0.1)
    assert info.value.status == 503
    assert len(script.requests) == 2


async def test_async_retry_and_lease_header() -> None:
    lease = {"detail": "held", "code": "leased"}
    script = Script(httpx.ConnectTimeout("slow"), (200, HEALTH), (409, lease))
    async with AsyncArmClient("http://x", token="t", lease="L1",
                              transport=httpx.MockTransport(script)) as c:
        assert (await c.health()).status == "ok"
        with pytest.raises(cl.Leased):
            await c.gripper("a", 0.5)
    last = script.requests[-1]
    assert last.headers["X-Arm-Lease"] == "L1" and last.headers["Authorization"] == "Bearer t"
    assert json.loads(last.content) == {"value": 0.5}


def test_error_without_code_maps_by_status() -> None:
    exc = cl.error_from_body(504, b"gateway timeout")
    assert isinstance(exc, cl.DeviceTimeout) and exc.detail == "gateway timeout"
    assert cl.error_from_body(418, b"").code == "error"


def test_telemetry_close_reasons_map_through_the_table() -> None:
    from websockets.exceptions import ConnectionClosedError, ConnectionClosedOK
    from websockets.frames import Close

    def closed(code: int, reason: str) -> Exception:
        return ConnectionClosedError(Close(code, reason), None)

    busy = cl.ws_close_error(closed(1013, '{"code":"busy","detail":"100 subscribers"}'))
    assert isinstance(busy, cl.Busy) and (busy.status, busy.detail) == (409, "100 subscribers")
    denied = cl.ws_close_error(closed(4401, "bad token"))
    assert isinstance(denied, cl.Unauthorized) and denied.status == 401
    assert isinstance(cl.ws_close_error(closed(1011, "oops")), cl.ConnectionFailed)
    assert cl.ws_close_error(ConnectionClosedOK(Close(1000, ""), None)) is None


# ---------------------------------------------------------------- command line


def test_cli_call_and_watch(server: Server, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["call", "rbe3001", "state", "--url", server.url]) == 0
    assert "positions" in json.loads(capsys.readouterr().out)
    assert cli_main(["call", "--url", server.url, "rbe3001", "move-pose", "0.2", "0.0", "0.1",
                     "--path", "line", "--wait"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "done"
    assert cli_main(["call", "--url", server.url, "rbe3001", "move-joints", "-0.2", "0.6",
                     "0.3", "--wait"]) == 0
    assert json.loads(capsys.readouterr().out)["status"] == "done"
    assert cli_main(["call", "--url", server.url, "angler", "ping"]) == 0
    assert len(json.loads(capsys.readouterr().out)["devices"]) == 4
    assert cli_main(["call", "--url", server.url, "rbe3001", "move-pose", "2", "2", "2"]) == 1
    err = json.loads(capsys.readouterr().err)
    assert (err["code"], err["status"]) == ("unreachable", 422)
    assert cli_main(["call", "--url", server.url, "rbe3001", "estop"]) == 0
    assert json.loads(capsys.readouterr().out) == {"estop": True}
    assert cli_main(["call", "--url", server.url, "rbe3001", "release"]) == 0
    assert json.loads(capsys.readouterr().out) == {"estop": False}
    # the joints' torque: the angler's winch falls without it, so off needs --load-supported
    # (the simulated world's hand holds the arm meanwhile: the module's server goes on)
    with ArmClient(server.url) as c:
        c.move_hand("angler", wait=True)
    assert cli_main(["call", "--url", server.url, "angler", "torque", "off"]) == 1
    assert json.loads(capsys.readouterr().err)["code"] == "in_use"
    def torque() -> list[int]:
        with ArmClient(server.url) as c:
            return [c.dxl_read_register("angler", i, "torque_enable").raw for i in (1, 2, 3, 4)]
    assert torque() == [1, 1, 1, 1]
    assert cli_main(["call", "--url", server.url, "angler", "torque", "off",
                     "--load-supported"]) == 0
    assert json.loads(capsys.readouterr().out) == {"arm": "angler", "on": False}
    assert torque() == [0, 0, 0, 0]
    assert cli_main(["call", "--url", server.url, "angler", "torque", "on"]) == 0
    assert json.loads(capsys.readouterr().out) == {"arm": "angler", "on": True}
    assert torque() == [1, 1, 1, 1]
    with ArmClient(server.url) as c:
        c.let_go_hand("angler")
    assert cli_main(["watch", "rbe3001", "--url", server.url, "--rate", "20",
                     "--count", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3 and all(line.startswith("seq ") and "tip=" in line for line in lines)
    seqs = [int(line.split()[1]) for line in lines]
    assert seqs == sorted(seqs)
