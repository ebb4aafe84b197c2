"""The classroom through the client and the CLI, against a real uvicorn server: queue_turn
(async and sync) joins, waits, claims and renews; the CLI's queue join/status/leave and audit."""

from __future__ import annotations

import csv
import io
import json
import threading
import time
from collections.abc import Iterator

import pytest
from _wait import wait_for

from app import client as cl
from app.client import ArmClient, AsyncArmClient
from app.client.cli import main as cli_main
from tests.test_client import Server, settings

ALICE, BOB, TEACH = "cc-alice", "cc-bob", "cc-teach"


@pytest.fixture(scope="module")
def room() -> Iterator[Server]:
    with Server(settings(operator_tokens=f"alice:{ALICE},bob:{BOB},client-test-operator",
                         instructor_tokens=f"teach:{TEACH}", claim_s=2.0, slot_s=2.5,
                         lease_ttl_s=1.0)) as srv:
        yield srv


def test_sync_queue_turns_one_after_the_other(room: Server) -> None:
    order: list[tuple[str, str, float]] = []
    errors: list[BaseException] = []

    def student(name: str, token: str) -> None:
        try:
            with ArmClient(room.url, token=token, timeout=30.0) as c, \
                    c.queue_turn("angler", poll=0.05, every=0.2, timeout=60.0) as keeper:
                order.append((name, "in", time.monotonic()))
                assert c.move_joints("angler", [0.0, 0.0, 0.0, 0.05], wait=True).status == "done"
                assert keeper.error is None
                time.sleep(0.3)  # the scenario: the turn is held a while after the move
                order.append((name, "out", time.monotonic()))
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    students = (("alice", ALICE), ("bob", BOB))
    threads = [threading.Thread(target=student, args=a) for a in students]
    with ArmClient(room.url, token=TEACH) as teach:
        for (name, _), t in zip(students, threads, strict=True):
            t.start()
            # the next student joins only once this one is in the queue (the order asserted
            # below is the order of joining, not of starting threads)
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline and not any(n == name for n, _, _ in order) \
                    and not any(e.name == name for e in teach.queue("angler").entries):
                time.sleep(0.02)
    for t in threads:
        t.join(timeout=60.0)
    assert not errors, errors
    assert [(n, w) for n, w, _ in order] == [("alice", "in"), ("alice", "out"), ("bob", "in"),
                                             ("bob", "out")]
    with ArmClient(room.url, token=TEACH) as t:
        me = t.me()
        assert (me.name, me.role) == ("teach", "instructor")
        names = [r.name for r in t.audit(arm="angler", limit=50)]
        assert "alice" in names and "bob" in names


async def test_async_queue_turn_and_slot_end(room: Server) -> None:
    async with AsyncArmClient(room.url, token=ALICE, timeout=30.0) as c, \
            AsyncArmClient(room.url, token=BOB, timeout=30.0) as b:
        async with c.queue_turn("rbe3001", poll=0.05, every=0.2, timeout=30.0) as keeper:
            assert c.leases["rbe3001"] == keeper.id
            bob = await b.join_queue("rbe3001")
            q = (await c.state("rbe3001")).positions
            m = await c.move_joints("rbe3001", [q[0] + 0.05, q[1], q[2]], wait=True)
            assert m.status == "done", m
            # past the 2.5 s slot: renewals stop, moves are refused
            await wait_for(lambda: keeper.error is not None, timeout=20.0, what="the slot end")
            assert isinstance(keeper.error, cl.NotFound), keeper.error
            with pytest.raises(cl.Leased):
                await c.move_joints("rbe3001", [0.0, 0.6, 0.3])
        assert "rbe3001" not in c.leases
        st = await c.queue("rbe3001")
        assert st.holder is None and st.entries[0].name == "bob"
        await b.leave_queue("rbe3001", bob.id)


def test_queue_turn_leaves_the_queue_when_it_gives_up(room: Server) -> None:
    with ArmClient(room.url, token=ALICE, timeout=30.0) as a, \
            ArmClient(room.url, token=BOB, timeout=30.0) as b, \
            a.queue_turn("angler", poll=0.05, every=0.2, timeout=30.0):
        with pytest.raises(TimeoutError), b.queue_turn("angler", poll=0.05, timeout=0.3):
            pass
        assert [e.name for e in b.queue("angler").entries] == ["alice"]


def test_cli_queue_and_audit(room: Server, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["call", "--url", room.url, "--token", BOB, "angler"]
    assert cli_main([*base, "queue", "join"]) == 0
    entry = json.loads(capsys.readouterr().out)
    assert entry["name"] == "bob"
    assert cli_main([*base, "queue", "status"]) == 0
    assert "bob" in [e["name"] for e in json.loads(capsys.readouterr().out)["entries"]]
    assert cli_main([*base, "queue", "leave", entry["id"]]) == 0
    assert json.loads(capsys.readouterr().out)["status"] in ("done", "expired")
    assert cli_main([*base, "audit"]) == 1  # not an instructor
    assert json.loads(capsys.readouterr().err)["code"] == "forbidden"
    assert cli_main(["call", "--url", room.url, "--token", TEACH, "angler", "audit",
                     "--who", "bob", "--csv"]) == 0
    rows = list(csv.reader(io.StringIO(capsys.readouterr().out)))
    assert rows[0][:3] == ["time", "name", "role"]
    assert {r[1] for r in rows[1:]} == {"bob"}
    assert any(r[4] == "DELETE" and "/queue/" in r[5] for r in rows[1:])
