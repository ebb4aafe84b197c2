"""Serial ports open exclusively (issue 11, item 7): a second link (a second server) on a port
that one holds is refused with an error naming the process that holds it, and the first link
keeps working; once the first closes, the port opens again. Over a real pseudo-terminal."""

from __future__ import annotations

import asyncio
import os
import tty

import pytest

from app.links.base import Link, LinkError, LinkState
from app.links.serial import SerialLink
from app.links.threaded import ThreadLink


@pytest.mark.parametrize("serial_link", [SerialLink, ThreadLink], ids=["asyncio", "thread"])
async def test_a_second_link_on_a_held_port_is_refused_naming_the_holder(
        serial_link: type[Link]) -> None:
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    first, second = serial_link(path), serial_link(path)
    try:
        await first.open()
        with pytest.raises(LinkError) as exc:
            await second.open()
        assert f"process {os.getpid()}" in str(exc.value)
        assert "in use" in str(exc.value) and path in str(exc.value)
        assert second.state is LinkState.DOWN and "in use" in (second.last_error or "")
        # The holder's link is untouched by the refused open.
        await first.write(b"ping")
        loop = asyncio.get_running_loop()
        assert await asyncio.wait_for(loop.run_in_executor(None, os.read, master, 16), 5) \
            == b"ping"
        os.write(master, b"pong")
        assert await first.read(2.0) == b"pong"
        await first.close()
        await second.open()
        assert second.state is LinkState.UP
    finally:
        await first.close()
        await second.close()
        os.close(master)
        os.close(slave)
