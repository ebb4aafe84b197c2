"""A small embedded SQLite store under ARMSERVER_DATA_DIR: settings that survive a restart.

One connection, owned by one writer thread; the event loop hands it jobs and awaits their
futures, so a slow disk or a locked database never blocks the loop (ARCHITECTURE rule 10).

- `settings(scope, key) -> JSON`: e.g. ("arm:rbe3001", "safety"). Later tables (audit log,
  queues: issue 14) are added as new entries of `MIGRATIONS`; `PRAGMA user_version` says how
  many have run.
- A write that fails (disk full, database locked by another process past the busy timeout, a
  read-only directory) is not lost: the newest value of each (scope, key) is kept in memory,
  answered by reads, and retried every RETRY_S and before every later write, until it lands.
  Meanwhile `health()` says what is wrong (`/api/v1/health`), and `put` answers False so the
  route can say "applied, not yet persisted".
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

DB_NAME = "armserver.sqlite3"
#: How long a write waits for another process's lock before it counts as failed, s. Short:
#: the failed write is kept and retried, and a stuck writer would delay the next request.
BUSY_TIMEOUT_S = 1.0
#: How often failed writes are retried, s.
RETRY_S = 5.0
#: Jobs waiting for the writer thread at most (bounded, rule 9).
MAX_JOBS = 1024

MIGRATIONS: list[str] = [
    """CREATE TABLE settings (
           scope TEXT NOT NULL,
           key TEXT NOT NULL,
           value TEXT NOT NULL,
           updated REAL NOT NULL,
           PRIMARY KEY (scope, key)
       )""",
    # issue 14: the audit log (app/audit.py); the queues live in `settings` ("queue:<arm>")
    """CREATE TABLE audit (
           seq INTEGER PRIMARY KEY AUTOINCREMENT,
           time REAL NOT NULL,
           name TEXT NOT NULL,
           role TEXT NOT NULL,
           arm TEXT,
           method TEXT NOT NULL,
           route TEXT NOT NULL,
           summary TEXT NOT NULL,
           status INTEGER NOT NULL,
           code TEXT
       )""",
    "CREATE INDEX audit_time ON audit (time)",
]

#: The columns of an audit record, in order.
AUDIT_COLUMNS = ("time", "name", "role", "arm", "method", "route", "summary", "status", "code")


class StoreError(Exception):
    pass


@dataclass(frozen=True)
class StoreHealth:
    ok: bool
    path: str
    pending: int
    error: str | None


class Store:
    """The server's database; `open()` at start-up, `close()` at shutdown."""

    def __init__(self, directory: str | Path, *, max_pages: int | None = None,
                 busy_timeout_s: float = BUSY_TIMEOUT_S, retry_s: float = RETRY_S) -> None:
        self.path = Path(directory) / DB_NAME
        self._max_pages = max_pages
        self._busy_timeout_s = busy_timeout_s
        self._retry_s = retry_s
        self._jobs: queue.Queue[tuple[Callable[[], Any], concurrent.futures.Future[Any]] | None]
        self._jobs = queue.Queue(MAX_JOBS)
        self._thread: threading.Thread | None = None
        self._db: sqlite3.Connection | None = None  # the writer thread's only
        self._pending: dict[tuple[str, str], str] = {}  # writer thread's; newest unsaved values
        self._error: str | None = None
        # audit records not yet on disk: appended by the loop, drained by the writer thread
        self._audit: list[tuple[Any, ...]] = []
        self._audit_lock = threading.Lock()
        self._audit_queued = False
        self.audit_written = 0

    # ------------------------------------------------------------ life

    def open(self) -> None:
        """Start the writer thread and open (create, migrate) the database. A database that
        cannot be opened is an error in `health()`, not a crash: the server runs on its
        profiles' settings and keeps changes in memory."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._worker, name="armserver-store",
                                            daemon=True)
            self._thread.start()
        self._call(self._open).result()

    def close(self) -> None:
        if self._thread is None:
            return
        try:
            self._call(self._flush).result(timeout=5.0)
            self._call(self._flush_audit).result(timeout=5.0)
        except (concurrent.futures.TimeoutError, StoreError):
            pass
        self._jobs.put(None)
        self._thread.join(timeout=5.0)
        self._thread = None

    def health(self) -> StoreHealth:
        return StoreHealth(ok=self._error is None, path=str(self.path),
                           pending=len(self._pending) + len(self._audit), error=self._error)

    # ------------------------------------------------------------ settings

    def get_setting_sync(self, scope: str, key: str) -> Any:
        """A setting's value (None if unset), blocking: for start-up, before the loop serves."""
        return self._call(lambda: self._get(scope, key)).result()

    async def get_setting(self, scope: str, key: str) -> Any:
        return await asyncio.wrap_future(self._call(lambda: self._get(scope, key)))

    async def put_setting(self, scope: str, key: str, value: Any) -> bool:
        """Save a JSON-able value; True when it is on disk, False when it is kept in memory to
        be retried (the reason is in `health()`)."""
        text = json.dumps(value, allow_nan=False, separators=(",", ":"))
        return await asyncio.wrap_future(self._call(lambda: self._put(scope, key, text)))

    def put_setting_nowait(self, scope: str, key: str, value: Any) -> None:
        """As `put_setting`, without waiting for the write (it lands in order with the others;
        a failed one is kept and retried)."""
        text = json.dumps(value, allow_nan=False, separators=(",", ":"))
        self._call(lambda: self._put(scope, key, text)).add_done_callback(_ignore)

    # ------------------------------------------------------------ audit log

    def audit(self, record: tuple[Any, ...]) -> None:
        """Append an audit record (AUDIT_COLUMNS, in order) without waiting: it is kept in
        memory until the writer thread has it on disk, retried like a setting when a write
        fails, and never dropped."""
        with self._audit_lock:
            self._audit.append(record)
            if self._audit_queued:
                return
            self._audit_queued = True
        fut = self._call(self._flush_audit)
        if fut.done() and fut.exception() is not None:  # not open, or the job queue full:
            with self._audit_lock:                       # the next record or retry takes it
                self._audit_queued = False
        fut.add_done_callback(_ignore)

    async def query_audit(self, *, arm: str | None = None, who: str | None = None,
                          since: float | None = None, until: float | None = None,
                          limit: int = 100) -> list[dict[str, Any]]:
        """Audit records newest first, those not yet on disk included."""
        return await asyncio.wrap_future(
            self._call(lambda: self._query_audit(arm, who, since, until, limit)))

    def _flush_audit(self) -> bool:
        with self._audit_lock:
            self._audit_queued = False
            rows = list(self._audit)
        if not rows:
            return True
        if self._db is None:
            self._open()
            if self._db is None:
                return False
        try:
            self._db.execute("BEGIN")
            self._db.executemany(
                f"INSERT INTO audit ({', '.join(AUDIT_COLUMNS)}) VALUES "
                f"({', '.join('?' * len(AUDIT_COLUMNS))})", rows)
            self._db.execute("COMMIT")
        except sqlite3.Error as exc:
            if self._db.in_transaction:
                self._db.execute("ROLLBACK")
            self._fail(f"writing {len(rows)} audit record(s) to {self.path}: {exc} (kept in "
                       f"memory, retried every {self._retry_s:g} s)")
            return False
        with self._audit_lock:
            del self._audit[:len(rows)]
        self.audit_written += len(rows)
        if not self._pending:
            self._ok()
        return True

    def _query_audit(self, arm: str | None, who: str | None, since: float | None,
                     until: float | None, limit: int) -> list[dict[str, Any]]:
        def keep(r: tuple[Any, ...]) -> bool:
            return ((arm is None or r[3] == arm) and (who is None or r[1] == who)
                    and (since is None or r[0] >= since) and (until is None or r[0] <= until))

        with self._audit_lock:
            unsaved = [r for r in self._audit if keep(r)]
        rows = list(reversed(unsaved))[:limit]
        if self._db is not None and len(rows) < limit:
            where, args = [], []
            for col, op, val in (("arm", "=", arm), ("name", "=", who), ("time", ">=", since),
                                 ("time", "<=", until)):
                if val is not None:
                    where.append(f"{col} {op} ?")
                    args.append(val)
            sql = (f"SELECT {', '.join(AUDIT_COLUMNS)} FROM audit"
                   f"{' WHERE ' + ' AND '.join(where) if where else ''} "
                   f"ORDER BY time DESC, seq DESC LIMIT ?")
            try:
                rows += self._db.execute(sql, (*args, limit - len(rows))).fetchall()
            except sqlite3.Error as exc:
                self._fail(f"reading the audit log: {exc}")
                raise StoreError(self._error or "read failed") from exc
        return [dict(zip(AUDIT_COLUMNS, r, strict=True)) for r in rows]

    # ------------------------------------------------------------ other tables (issue 14)

    async def run(self, fn: Callable[[sqlite3.Connection], T]) -> T:
        """Run `fn(connection)` on the writer thread (the one place the connection is used):
        for tables added by later MIGRATIONS, e.g. an audit log. StoreError if the database is
        not open; sqlite3 errors propagate (and are the caller's to report)."""

        def job() -> T:
            if self._db is None:
                raise StoreError(self._error or "the database is not open")
            return fn(self._db)

        return await asyncio.wrap_future(self._call(job))

    # ------------------------------------------------------------ the writer thread

    def _call(self, fn: Callable[[], T]) -> concurrent.futures.Future[T]:
        fut: concurrent.futures.Future[T] = concurrent.futures.Future()
        if self._thread is None:
            fut.set_exception(StoreError("the store is not open"))
            return fut
        try:
            self._jobs.put_nowait((fn, fut))
        except queue.Full:
            fut.set_exception(StoreError(f"the store has {MAX_JOBS} jobs waiting"))
        return fut

    def _worker(self) -> None:
        while True:
            try:
                job = self._jobs.get(timeout=self._retry_s if self._pending or self._audit
                                     else None)
            except queue.Empty:
                self._flush()
                self._flush_audit()
                continue
            if job is None:
                break
            fn, fut = job
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn())
            except Exception as exc:  # the caller gets it, the thread lives on  # noqa: BLE001
                fut.set_exception(exc)
        if self._db is not None:
            self._db.close()
            self._db = None

    def _open(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(self.path, timeout=self._busy_timeout_s,
                                 isolation_level=None, check_same_thread=False)
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            if self._max_pages is not None:
                db.execute(f"PRAGMA max_page_count={int(self._max_pages)}")
            version = db.execute("PRAGMA user_version").fetchone()[0]
            for i, sql in enumerate(MIGRATIONS[version:], start=version + 1):
                db.execute("BEGIN IMMEDIATE")
                db.execute(sql)
                db.execute(f"PRAGMA user_version={i}")
                db.execute("COMMIT")
            self._db = db
            self._ok()
        except (sqlite3.Error, OSError) as exc:
            self._fail(f"cannot open {self.path}: {exc}")

    def _get(self, scope: str, key: str) -> Any:
        text = self._pending.get((scope, key))
        if text is None and self._db is not None:
            try:
                row = self._db.execute("SELECT value FROM settings WHERE scope = ? AND key = ?",
                                       (scope, key)).fetchone()
            except sqlite3.Error as exc:
                self._fail(f"reading {scope}/{key}: {exc}")
                raise StoreError(self._error or "read failed") from exc
            text = row[0] if row is not None else None
        return None if text is None else json.loads(text)

    def _put(self, scope: str, key: str, text: str) -> bool:
        self._pending[(scope, key)] = text
        return self._flush()

    def _flush(self) -> bool:
        """Write every pending value; True when none is left."""
        if self._db is None:
            self._open()
            if self._db is None:
                return False
        while self._pending:
            (scope, key), text = next(iter(self._pending.items()))
            try:
                self._db.execute(
                    "INSERT INTO settings (scope, key, value, updated) "
                    "VALUES (?, ?, ?, ?) ON CONFLICT (scope, key) DO "
                    "UPDATE SET value = excluded.value, updated = excluded.updated",
                    (scope, key, text, time.time()))
            except sqlite3.Error as exc:
                self._fail(f"writing {scope}/{key} to {self.path}: {exc} "
                           f"({len(self._pending)} change(s) kept in memory, retried every "
                           f"{self._retry_s:g} s)")
                return False
            if self._pending.get((scope, key)) == text:
                del self._pending[(scope, key)]
        self._ok()
        return True

    def _fail(self, why: str) -> None:
        if self._error != why:
            log.error("store: %s", why)
        self._error = why

    def _ok(self) -> None:
        if self._error is not None:
            log.info("store: writes land again (%s)", self.path)
        self._error = None


def _ignore(fut: concurrent.futures.Future[Any]) -> None:
    """Done-callback of a fire-and-forget job: its failure is already in `health()`."""
    if not fut.cancelled():
        fut.exception()
