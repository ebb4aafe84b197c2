"""A real Mosquitto broker for the MQTT tests and the bench: Debian's `mosquitto` binary on a
free loopback port, its config (and password file, if any) in a temp dir. It can be killed
(SIGKILL, like a crash) and started again on the same port. Found as tests/_deps.py finds it;
tests skip when it is missing (a failure under ARMSERVER_STRICT_SKIPS=1, as in CI), and `make test`
installs it or fails.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

from _deps import MOSQUITTO, MOSQUITTO_PASSWD


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broker:
    """`Broker(tmp_path).start()`; `.port`, `.ws_port`; `.kill()`, `.start()` again; `.stop()`."""

    def __init__(self, workdir: Path, users: dict[str, str] | None = None,
                 websockets: bool = False, extra: str = "") -> None:
        if MOSQUITTO is None:
            raise RuntimeError("mosquitto is not installed (make mosquitto)")
        self.dir = workdir
        self.port = free_port()
        self.ws_port = free_port() if websockets else None
        lines = ["persistence false", "log_dest stderr", "log_type error", "log_type warning",
                 f"listener {self.port} 127.0.0.1"]
        if os.geteuid() == 0:  # else it drops to user mosquitto, who cannot read our temp dir
            lines.append("user root")
        if users:
            assert MOSQUITTO_PASSWD is not None, "mosquitto_passwd is missing"
            pw = workdir / "passwd"
            pw.write_text("")
            for user, password in users.items():
                subprocess.run([MOSQUITTO_PASSWD, "-b", str(pw), user, password], check=True,
                               capture_output=True)
            pw.chmod(0o600)
            lines += ["allow_anonymous false", f"password_file {pw}"]
        else:
            lines.append("allow_anonymous true")
        if self.ws_port is not None:
            lines += [f"listener {self.ws_port} 127.0.0.1", "protocol websockets"]
        self.conf = workdir / "mosquitto.conf"
        self.conf.write_text("\n".join(lines) + "\n" + extra)
        self.log = workdir / "mosquitto.log"
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> Broker:
        assert MOSQUITTO is not None
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen([MOSQUITTO, "-c", str(self.conf)], stdout=log,
                                         stderr=subprocess.STDOUT)
        deadline = time.monotonic() + 10
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"mosquitto exited: {self.log.read_text()[-2000:]}")
            with contextlib.suppress(OSError), socket.create_connection(
                    ("127.0.0.1", self.port), timeout=0.2):
                if self.ws_port is None:
                    return self
                with socket.create_connection(("127.0.0.1", self.ws_port), timeout=0.2):
                    return self
            if time.monotonic() > deadline:
                raise RuntimeError("mosquitto did not listen in 10 s")
            time.sleep(0.02)

    def kill(self) -> None:
        """SIGKILL, as a crash: no goodbye to any client."""
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(5)
            self.proc = None

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
            self.proc = None


@contextlib.contextmanager
def running_broker(workdir: Path, **kw: object) -> Iterator[Broker]:
    broker = Broker(workdir, **kw).start()  # type: ignore[arg-type]
    try:
        yield broker
    finally:
        broker.stop()
