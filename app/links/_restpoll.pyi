"""Types of the rounds in C (app/links/_restpoll.c: its module doc says what they do)."""

from app.links.poller import RestPlan as _Plan

_End = tuple[str, bytes, float, float] | tuple[str, str] | None

def run(links: list[_Plan], wake_fd: int, early: float, catch_up: float, write_wait: float,
        chunk: int, /) -> list[tuple[float, list[float], _End]]: ...
