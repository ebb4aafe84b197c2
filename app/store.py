"""A small embedded SQLite store under ARMSERVER_DATA_DIR: settings and the audit log, across
restarts.

One connection, owned by one writer thread; the event loop hands it jobs and awaits their
futures, so a slow disk or a locked database never blocks the loop (ARCHITECTURE rule 10).

- `settings(scope, key) -> JSON`: e.g. ("arm:rbe3001", "safety"). Later tables are added as
  new entries of `MIGRATIONS`; `PRAGMA user_version` says how many have run.
- A write that fails (disk full, database locked by another process past the busy timeout, a
  read-only directory) is not lost: the newest value of each (scope, key) is kept in memory,
  answered by reads, and retried every RETRY_S and before every later write, until it lands.
  Meanwhile `health()` says what is wrong (`/api/v1/health`), and `put` answers False so the
  route can say "applied, not yet persisted".
- The audit log (app/classroom/audit.py decides what is recorded): an `AuditEntry` is appended
without
  waiting and may change after (a request's start record gets its status when the request
  ends; a refusal summary counts on). The writer thread writes what is new or changed at most
  AUDIT_FLUSH_S after it happened, in one transaction: a start record is in the database file
  that soon, so a kill -9 keeps the attempt. Records the disk refuses wait in memory, at most
  `max_pending` of them: beyond that the oldest are dropped and counted, the count shows in
  `health().error` and, once the disk takes writes again, as a `dropped` record. The table
  keeps at most `audit_max_rows` rows: the oldest beyond are deleted.
- The data folder is made 0700 and the database files (with their -wal and -shm) 0600: the
  log names people and what they did.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import os
import queue
import sqlite3
import stat
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger(__name__)

T = TypeVar("T")

#: The scope of an arm's own settings (`ARM_SCOPE.format(name)`): its safety envelope
#: (app/web/routes/safety.py), its estop latch (app/service.py).
ARM_SCOPE = "arm:{}"
#: The scope of a camera's own settings (`CAMERA_SCOPE.format(name)`): its calibration
#: (CALIBRATION_KEY, app/cameras/hub.py; a lab's front reads whether one is there).
CAMERA_SCOPE = "camera:{}"
CALIBRATION_KEY = "calibration"
#: The key of an arm's estop latch record under ARM_SCOPE (`latch_record`; `put_latch`,
#: `latch_of`).
ESTOP_KEY = "estop"
#: Longest an estop press's answer waits for its latch record to be on disk, s: a disk that
#: holds it longer does not hold the answer back (the store retries; health says).
LATCH_SAVE_WAIT_S = 0.5
DB_NAME = "armserver.sqlite3"
#: The files SQLite keeps beside the database (all made 0600 like it).
DB_FILES = (DB_NAME, f"{DB_NAME}-wal", f"{DB_NAME}-shm", f"{DB_NAME}-journal")
#: How long a write waits for another process's lock before it counts as failed, s. Short:
#: the failed write is kept and retried, and a stuck writer would delay the next request.
BUSY_TIMEOUT_S = 1.0
#: How often failed writes are retried, s.
RETRY_S = 5.0
#: Jobs waiting for the writer thread at most (bounded, rule 9).
MAX_JOBS = 1024
#: How long a new or changed audit record waits for others to share its transaction, s: the
#: bound on how late a request's start record reaches the database file (a kill -9 after that
#: keeps it), and one transaction per 0.1 s rather than one per request under a burst.
AUDIT_FLUSH_S = 0.1
#: Audit records kept in memory while the disk refuses them, at most (then the oldest go).
AUDIT_MAX_PENDING = 10_000
#: Audit rows kept in the database, at most (the settings' default; then the oldest go).
AUDIT_MAX_ROWS = 100_000
#: Audit records written in one transaction at most.
AUDIT_BATCH = 1000
#: The code of a start record whose request never ended: the server died under it.
INTERRUPTED = "interrupted"

_AUDIT_V2 = """CREATE TABLE audit_v2 (
           seq INTEGER PRIMARY KEY AUTOINCREMENT,
           time REAL NOT NULL,
           name TEXT NOT NULL,
           role TEXT NOT NULL,
           arm TEXT,
           method TEXT NOT NULL,
           route TEXT NOT NULL,
           summary TEXT NOT NULL,
           status INTEGER,
           code TEXT,
           kind TEXT NOT NULL DEFAULT 'request',
           count INTEGER NOT NULL DEFAULT 1,
           ended REAL,
           address TEXT
       )"""
_V1_COLUMNS = "seq, time, name, role, arm, method, route, summary, status, code"

MIGRATIONS: list[str] = [
    """CREATE TABLE settings (
           scope TEXT NOT NULL,
           key TEXT NOT NULL,
           value TEXT NOT NULL,
           updated REAL NOT NULL,
           PRIMARY KEY (scope, key)
       )""",
    # issue 14: the audit log (app/classroom/audit.py); the queues live in `settings`
    # ("queue:<arm>")
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
    # issue 22: a start record has no status yet; refusal summaries (kind, count, ended); the
    # caller's address. SQLite cannot drop a NOT NULL: the table is copied (one step each)
    _AUDIT_V2,
    f"INSERT INTO audit_v2 ({_V1_COLUMNS}) SELECT {_V1_COLUMNS} FROM audit",
    "DROP TABLE audit",
    "ALTER TABLE audit_v2 RENAME TO audit",
    "CREATE INDEX audit_time ON audit (time)",
]

#: The columns of an audit record, in order.
AUDIT_COLUMNS = ("time", "name", "role", "arm", "method", "route", "summary", "status", "code",
                 "kind", "count", "ended", "address")
_INSERT = (f"INSERT INTO audit ({', '.join(AUDIT_COLUMNS)}) "
           f"VALUES ({', '.join('?' * len(AUDIT_COLUMNS))})")
_UPDATE = f"UPDATE audit SET {', '.join(f'{c} = ?' for c in AUDIT_COLUMNS)} WHERE seq = ?"


class StoreError(Exception):
    pass


@dataclass(frozen=True)
class StoreHealth:
    ok: bool
    path: str
    pending: int
    error: str | None


@dataclass(eq=False, slots=True)
class AuditEntry:
    """One audit record (AUDIT_COLUMNS) and where it stands. Made and changed on the event loop
    only through `Store.audit` / `audit_update` / `audit_cancel` (which hold the store's audit
    lock while the writer thread reads it)."""

    time: float
    name: str
    role: str
    arm: str | None
    method: str
    route: str
    summary: str
    status: int | None
    code: str | None
    #: "request": one request (status None while it runs); "refusals": refused requests of one
    #: address and reason counted over an interval (`time` the first, `ended` the last);
    #: "dropped": records lost to the memory bound while the disk refused them.
    kind: str = "request"
    count: int = 1
    ended: float | None = None
    address: str | None = None
    seq: int | None = field(default=None, repr=False)  # its row, once written
    version: int = field(default=0, repr=False)  # +1 on every change
    cancelled: bool = field(default=False, repr=False)  # to be deleted (or never written)
    dropped: bool = field(default=False, repr=False)  # lost to the memory bound

    def row(self) -> tuple[Any, ...]:
        return (self.time, self.name, self.role, self.arm, self.method, self.route,
                self.summary, self.status, self.code, self.kind, self.count, self.ended,
                self.address)


class Store:
    """The server's database; `open()` at start-up, `close()` at shutdown."""

    def __init__(self, directory: str | Path, *, max_pages: int | None = None,
                 busy_timeout_s: float = BUSY_TIMEOUT_S, retry_s: float = RETRY_S,
                 audit_max_rows: int = AUDIT_MAX_ROWS, max_pending: int = AUDIT_MAX_PENDING,
                 flush_s: float = AUDIT_FLUSH_S) -> None:
        self.path = Path(directory) / DB_NAME
        self._max_pages = max_pages
        self._busy_timeout_s = busy_timeout_s
        self._retry_s = retry_s
        self._max_rows = audit_max_rows
        self._max_pending = max(1, max_pending)
        self._flush_s = flush_s
        self._jobs: queue.Queue[tuple[Callable[[], Any], concurrent.futures.Future[Any]] | None]
        self._jobs = queue.Queue(MAX_JOBS)
        self._thread: threading.Thread | None = None
        self._db: sqlite3.Connection | None = None  # the writer thread's only
        self._pending: dict[tuple[str, str], str] = {}  # writer thread's; newest unsaved values
        self._retry_at = 0.0  # writer thread's: monotonic time of the next settings retry
        self._error: str | None = None
        # audit entries, by id(): new ones (insertion order: oldest first), the batch being
        # written, written ones changed since, written ones to delete. Under _audit_lock.
        self._audit: dict[int, AuditEntry] = {}
        self._inflight: dict[int, AuditEntry] = {}
        self._changed: dict[int, AuditEntry] = {}
        self._deletes: dict[int, AuditEntry] = {}
        self._lost: AuditEntry | None = None  # the `dropped` record not yet written
        self._audit_due: float | None = None  # monotonic time the next audit write is due
        self._audit_lock = threading.Lock()
        self._rows = 0  # writer thread's: rows in the audit table
        self.audit_written = 0
        self.audit_dropped = 0
        self.audit_trimmed = 0

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
            self._call(self._drain_audit).result(timeout=5.0)
        except (concurrent.futures.TimeoutError, StoreError):
            pass
        self._jobs.put(None)
        self._thread.join(timeout=5.0)
        self._thread = None

    def health(self) -> StoreHealth:
        with self._audit_lock:
            audit = (len(self._audit) + len(self._inflight) + len(self._changed)
                     + len(self._deletes))
            lost = self._lost.count if self._lost is not None else 0
        error = self._error
        if lost:
            error = (f"{error or 'the audit log waits for the disk'}; {lost} audit record(s) "
                     f"dropped (more than {self._max_pending} waited in memory)")
        return StoreHealth(ok=error is None, path=str(self.path),
                           pending=len(self._pending) + audit, error=error)

    def settings_pending(self) -> int:
        """Settings not yet written (of `health().pending`: a request's own in-flight audit
        record is pending while it runs, and says nothing of whether a setting is on disk)."""
        return len(self._pending)

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

    def put_setting_nowait(self, scope: str, key: str, value: Any
                           ) -> concurrent.futures.Future[bool]:
        """As `put_setting`, without waiting for the write (it lands in order with the others;
        a failed one is kept and retried). The write's future, for a caller that wants to know
        later (its outcome needs no reading)."""
        text = json.dumps(value, allow_nan=False, separators=(",", ":"))
        fut = self._call(lambda: self._put(scope, key, text))
        fut.add_done_callback(_ignore)
        return fut

    # ------------------------------------------------------------ an arm's estop latch

    def latch_of(self, arm: str) -> Any:
        """`arm`'s estop latch record (`latch_record`; None: none), blocking: for start-up."""
        return self.get_setting_sync(ARM_SCOPE.format(arm), ESTOP_KEY)

    def put_latch(self, arm: str, latched: bool) -> concurrent.futures.Future[bool]:
        """Record `arm`'s estop latch (now) without waiting: the write's future, for
        `saved_within`. Written by the arm's service at each latch and release, and by a lab's
        front for a press it keeps while the arm's worker is down."""
        return self.put_setting_nowait(ARM_SCOPE.format(arm), ESTOP_KEY, latch_record(latched))

    # ------------------------------------------------------------ audit log (event loop side)

    def audit(self, record: AuditEntry | tuple[Any, ...]) -> AuditEntry:
        """Append an audit record without waiting (an `AuditEntry`, or a tuple of its first
        columns in AUDIT_COLUMNS' order); it is written within AUDIT_FLUSH_S. Keep the entry to
        change it later (`audit_update`, `audit_cancel`)."""
        entry = record if isinstance(record, AuditEntry) else AuditEntry(*record)
        with self._audit_lock:
            self._audit[id(entry)] = entry
            while len(self._audit) > self._max_pending:
                self._drop_oldest()
            self._schedule()
        return entry

    def audit_update(self, entry: AuditEntry, **values: Any) -> None:
        """Change fields of an entry (e.g. `status`, `code`, `ended` when its request ends):
        in memory at once, in the database within AUDIT_FLUSH_S."""
        with self._audit_lock:
            for name, value in values.items():
                setattr(entry, name, value)
            entry.version += 1
            if entry.dropped or entry.cancelled:
                return
            if entry.seq is not None:
                self._changed[id(entry)] = entry
                self._schedule()

    def audit_cancel(self, entry: AuditEntry) -> None:
        """Take an entry back: never written if it is not yet, deleted if it is."""
        with self._audit_lock:
            entry.cancelled = True
            entry.version += 1
            if self._audit.pop(id(entry), None) is not None:
                return
            if entry.seq is not None:
                self._changed.pop(id(entry), None)
                self._deletes[id(entry)] = entry
                self._schedule()

    async def query_audit(self, *, arm: str | None = None, who: str | None = None,
                          since: float | None = None, until: float | None = None,
                          limit: int = 100) -> list[dict[str, Any]]:
        """Audit records newest first, as they stand now (those not yet on disk included)."""
        return await asyncio.wrap_future(
            self._call(lambda: self._query_audit(arm, who, since, until, limit)))

    def _schedule(self) -> None:
        """(Lock held.) Have the writer write the audit changes within AUDIT_FLUSH_S."""
        if self._audit_due is None:
            self._audit_due = time.monotonic() + self._flush_s
            self._wake()

    def _drop_oldest(self) -> None:
        """(Lock held.) Drop the oldest unsaved entry (never the `dropped` record itself)."""
        key = next((k for k, e in self._audit.items() if e is not self._lost), None)
        if key is None:
            return
        entry = self._audit.pop(key)
        entry.dropped = True
        self.audit_dropped += 1
        now = time.time()
        if self._lost is None:
            self._lost = AuditEntry(now, "(server)", "none", None, "-", "-", "", None, None,
                                    kind="dropped", count=0)
            self._audit = {id(self._lost): self._lost, **self._audit}
        self._lost.count += 1
        self._lost.ended = now
        self._lost.version += 1
        self._lost.summary = (f"{self._lost.count} audit record(s) lost: the database refused "
                              f"writes while more than {self._max_pending} waited in memory")

    # ------------------------------------------------------------ audit log (writer side)

    def _flush_audit(self) -> bool:
        """Write what is new, changed or cancelled in one transaction; True when it landed."""
        with self._audit_lock:
            self._audit_due = None
            batch: list[tuple[AuditEntry, int, tuple[Any, ...]]] = []
            for key in list(self._audit)[:AUDIT_BATCH]:
                entry = self._audit.pop(key)
                if not entry.cancelled:  # (cancelled while a failed write had it)
                    self._inflight[key] = entry
                    batch.append((entry, entry.version, entry.row()))
            changed = [(e, e.version, e.row()) for e in self._changed.values()]
            deletes = [(e, e.seq) for e in self._deletes.values()]
        if not (batch or changed or deletes):
            return True
        if self._db is None:
            self._open()
        rows = self._rows
        seqs: list[int] = []
        try:
            if self._db is None:
                raise sqlite3.OperationalError(self._error or "the database is not open")
            self._db.execute("BEGIN")
            for _, _, row in batch:
                seqs.append(int(self._db.execute(_INSERT, row).lastrowid or 0))
            rows += len(batch)
            self._db.executemany(_UPDATE, [(*row, e.seq) for e, _, row in changed])
            for _, seq in deletes:
                rows -= self._db.execute("DELETE FROM audit WHERE seq = ?", (seq,)).rowcount
            trimmed = 0
            if rows > self._max_rows:
                trimmed = self._db.execute(
                    "DELETE FROM audit WHERE seq IN (SELECT seq FROM audit ORDER BY seq "
                    "LIMIT ?)", (rows - self._max_rows,)).rowcount
            self._db.execute("COMMIT")
        except sqlite3.Error as exc:
            if self._db is not None and self._db.in_transaction:
                self._db.execute("ROLLBACK")
            with self._audit_lock:  # back in front of the newer ones, under the same bound
                self._audit = {**self._inflight, **self._audit}
                self._inflight.clear()
                while len(self._audit) > self._max_pending:
                    self._drop_oldest()
                self._audit_due = time.monotonic() + self._retry_s
            self._fail(f"writing {len(batch) + len(changed) + len(deletes)} audit record "
                       f"change(s) to {self.path}: {exc} (kept in memory, retried every "
                       f"{self._retry_s:g} s)")
            return False
        self._rows = rows - trimmed
        self.audit_trimmed += trimmed
        with self._audit_lock:
            self._inflight.clear()
            for (entry, version, _), seq in zip(batch, seqs, strict=True):
                entry.seq = seq
                if entry is self._lost:
                    self._lost = None
                if entry.cancelled:
                    self._deletes[id(entry)] = entry
                elif entry.version != version and not entry.dropped:
                    self._changed[id(entry)] = entry
            for entry, version, _ in changed:
                if entry.version == version:
                    self._changed.pop(id(entry), None)
            for entry, _ in deletes:
                self._deletes.pop(id(entry), None)
            if self._audit or self._changed or self._deletes:
                self._audit_due = time.monotonic()
        self.audit_written += len(batch)
        if not self._pending:
            self._ok()
        return True

    def _drain_audit(self) -> None:
        """Write every audit change (at shutdown), batch after batch, until one fails."""
        while self._flush_audit():
            with self._audit_lock:
                if not (self._audit or self._changed or self._deletes):
                    return

    def _query_audit(self, arm: str | None, who: str | None, since: float | None,
                     until: float | None, limit: int) -> list[dict[str, Any]]:
        def keep(e: AuditEntry) -> bool:
            return ((arm is None or e.arm == arm) and (who is None or e.name == who)
                    and (since is None or e.time >= since) and (until is None or e.time <= until))

        with self._audit_lock:
            unsaved = [e.row() for e in self._audit.values() if keep(e) and not e.cancelled]
            newer = {e.seq: e.row() for e in self._changed.values()}
            gone = {e.seq for e in self._deletes.values()}
        rows = sorted(unsaved, key=lambda r: -r[0])[:limit]
        if self._db is not None:
            where, args = [], []
            for col, op, val in (("arm", "=", arm), ("name", "=", who), ("time", ">=", since),
                                 ("time", "<=", until)):
                if val is not None:
                    where.append(f"{col} {op} ?")
                    args.append(val)
            sql = (f"SELECT seq, {', '.join(AUDIT_COLUMNS)} FROM audit"
                   f"{' WHERE ' + ' AND '.join(where) if where else ''} "
                   f"ORDER BY time DESC, seq DESC LIMIT ?")
            try:
                saved = self._db.execute(sql, (*args, limit + len(gone))).fetchall()
            except sqlite3.Error as exc:
                self._fail(f"reading the audit log: {exc}")
                raise StoreError(self._error or "read failed") from exc
            rows += [newer.get(r[0], r[1:]) for r in saved if r[0] not in gone]
            rows.sort(key=lambda r: -r[0])  # stable: the unsaved first among equal times
        return [dict(zip(AUDIT_COLUMNS, r, strict=True)) for r in rows[:limit]]

    # ------------------------------------------------------------ other tables (issue 14)

    async def run(self, fn: Callable[[sqlite3.Connection], T]) -> T:
        """Run `fn(connection)` on the writer thread (the one place the connection is used):
        for tables added by later MIGRATIONS. StoreError if the database is not open; sqlite3
        errors propagate (and are the caller's to report)."""

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

    def _wake(self) -> None:
        """Have the writer thread look at its deadlines now (a full queue wakes it anyway)."""
        self._call(_nothing).add_done_callback(_ignore)

    def _worker(self) -> None:
        while True:
            due = [t for t in (self._audit_due, self._retry_at if self._pending else None)
                   if t is not None]
            try:
                job = self._jobs.get(timeout=max(0.0, min(due) - time.monotonic())
                                     if due else None)
            except queue.Empty:
                pass
            else:
                if job is None:
                    break
                fn, fut = job
                if fut.set_running_or_notify_cancel():
                    try:
                        fut.set_result(fn())
                    except Exception as exc:  # the caller gets it, the thread lives on  # noqa: BLE001
                        fut.set_exception(exc)
            now = time.monotonic()
            if self._pending and now >= self._retry_at:
                self._flush()
            if self._audit_due is not None and now >= self._audit_due:
                self._flush_audit()
        if self._db is not None:
            self._db.close()
            self._db = None

    def _open(self) -> None:
        try:
            self._secure()
            db = sqlite3.connect(self.path, timeout=self._busy_timeout_s,
                                 isolation_level=None, check_same_thread=False)
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            if self._max_pages is not None:
                db.execute(f"PRAGMA max_page_count={int(self._max_pages)}")
            version = db.execute("PRAGMA user_version").fetchone()[0]
            for i, sql in enumerate(MIGRATIONS[version:], start=version + 1):
                db.execute("BEGIN IMMEDIATE")
                # another process on the same file (a lab's workers, app/lab) may have run it
                # between our read of user_version and this lock
                if db.execute("PRAGMA user_version").fetchone()[0] >= i:
                    db.execute("COMMIT")
                    continue
                db.execute(sql)
                db.execute(f"PRAGMA user_version={i}")
                db.execute("COMMIT")
            # start records an earlier process left open: it died before their requests ended
            db.execute("UPDATE audit SET code = ? WHERE kind = 'request' AND status IS NULL "
                       "AND code IS NULL", (INTERRUPTED,))
            self._rows = db.execute("SELECT count(*) FROM audit").fetchone()[0]
            self._db = db
            self._ok()
        except (sqlite3.Error, OSError) as exc:
            self._fail(f"cannot open {self.path}: {exc}")

    def _secure(self) -> None:
        """The data folder 0700 (when this user owns it and it is no shared sticky folder like
        /tmp), the database files 0600. A new database is made 0600, and SQLite gives its -wal
        and -shm the database's mode. A mode that cannot be changed (a read-only file system)
        is logged, not fatal."""
        folder = self.path.parent
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        try:
            os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        except FileExistsError:
            pass
        st = folder.stat()
        own = st.st_uid == os.geteuid() and not st.st_mode & stat.S_ISVTX
        for path, mode in ((folder, 0o700), *((folder / n, 0o600) for n in DB_FILES)):
            try:
                now = stat.S_IMODE(path.stat().st_mode)
                if now & 0o077 and (path != folder or own):
                    path.chmod(mode)
                    log.warning("store: %s was open to others (mode %o): made %o", path, now,
                                mode)
            except FileNotFoundError:
                continue
            except OSError as exc:
                log.warning("store: cannot make %s %o: %s", path, mode, exc)

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
        self._retry_at = time.monotonic() + self._retry_s
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
        with self._audit_lock:
            if self._audit_due is not None:  # a write landed: audit records waiting go too
                self._audit_due = min(self._audit_due, time.monotonic())
                return True
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


def latch_record(latched: bool) -> dict[str, Any]:
    """An estop latch record (ESTOP_KEY): whether latched, and since when (UTC)."""
    return {"latched": latched, "at": datetime.now(UTC).isoformat(timespec="milliseconds")}


async def saved_within(fut: concurrent.futures.Future[bool] | None,
                       seconds: float = LATCH_SAVE_WAIT_S) -> None:
    """Until a `put_setting_nowait` write is done, `seconds` at most (its outcome is the
    store's: a failed write is retried and said in `health()`)."""
    if fut is not None and not fut.done():
        await asyncio.wait({asyncio.wrap_future(fut)}, timeout=seconds)


def _nothing() -> None:
    """A job that only wakes the writer thread (to look at its deadlines)."""


def _ignore(fut: concurrent.futures.Future[Any]) -> None:
    """Done-callback of a fire-and-forget job: its failure is already in `health()`."""
    if not fut.cancelled():
        fut.exception()
