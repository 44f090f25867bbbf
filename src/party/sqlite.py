"""SQLite content caches (``party.text.cache.PartTextCache``, ``party.text.store.EmbeddingCache``).

One setup for both: the parent folder is created, the database opened in WAL mode with
``synchronous=NORMAL`` (a commit survives a crash of the process; SQLite's journal keeps the
file consistent), the schema created if absent, and a file that is not a usable database
reported by name; damage found later, by any query (``database disk image is malformed``),
is reported with the file and how to recover too. Subclasses set ``schema`` (CREATE TABLE IF NOT EXISTS statements), ``kind``
(for the error) and optionally ``hint`` (appended to it).
"""
from __future__ import annotations

import sqlite3
from collections.abc import Iterator, Sequence
from pathlib import Path


def connect(path: str | Path, schema: Sequence[str], kind: str, hint: str = "") -> sqlite3.Connection:
    """Open (creating) the cache database at ``path`` and its ``schema``, in one transaction."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    db = None
    try:
        db = sqlite3.connect(path)
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        with db:
            for statement in schema:
                db.execute(statement)
    except sqlite3.DatabaseError as e:
        if db is not None:
            db.close()
        raise sqlite3.DatabaseError(f"{path}: not a usable {kind} ({e}); delete it to rebuild{hint}") from e
    return db


def _damaged(e: sqlite3.DatabaseError) -> bool:
    """Corruption (not a lock, a constraint or a programming error)."""
    return type(e) is sqlite3.DatabaseError or "malformed" in str(e) or "not a database" in str(e)


class GuardedConnection:
    """A ``sqlite3.Connection`` whose corruption errors name the file and the way out."""

    def __init__(self, db: sqlite3.Connection, path: Path, kind: str, hint: str):
        self._db, self.path, self.kind, self.hint = db, path, kind, hint

    def _raise(self, e: sqlite3.DatabaseError):
        if not _damaged(e):
            raise e
        raise sqlite3.DatabaseError(
            f"{self.path}: the {self.kind} is damaged ({e}). Salvage what is readable with "
            f"`sqlite3 {self.path} .recover | sqlite3 {self.path}.recovered` and move that file "
            f"in its place, or delete it to rebuild{self.hint}") from e

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except sqlite3.DatabaseError as e:
            self._raise(e)

    def execute(self, *args) -> "GuardedCursor":
        return GuardedCursor(self._guard(self._db.execute, *args), self)

    def executemany(self, *args):
        return GuardedCursor(self._guard(self._db.executemany, *args), self)

    def __enter__(self):
        self._db.__enter__()
        return self

    def __exit__(self, *exc):
        return self._guard(self._db.__exit__, *exc)

    def close(self) -> None:
        self._db.close()


class GuardedCursor:
    def __init__(self, cursor: sqlite3.Cursor, conn: GuardedConnection):
        self._cursor, self._conn = cursor, conn

    def fetchone(self):
        return self._conn._guard(self._cursor.fetchone)

    def fetchall(self):
        return self._conn._guard(self._cursor.fetchall)

    def __iter__(self):
        while True:
            row = self.fetchone()
            if row is None:
                return
            yield row


def select_in(db, query: str, args: Sequence, keys: Sequence, chunk: int) -> Iterator[tuple]:
    """Rows of ``query`` (which ends in ``IN ({})``) for ``args`` and every key of ``keys``, asked
    ``chunk`` keys at a time (SQLite limits the number of host parameters per statement)."""
    for i in range(0, len(keys), chunk):
        part = list(keys[i:i + chunk])
        yield from db.execute(query.format(",".join("?" * len(part))), [*args, *part])


class SQLiteCache:
    """A cache file opened by ``connect``; closes on ``close()`` or at the end of a ``with``."""

    schema: Sequence[str] = ()
    kind = "cache"
    hint = ""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.db = GuardedConnection(connect(self.path, self.schema, self.kind, self.hint),
                                    self.path, self.kind, self.hint)

    def close(self) -> None:
        self.db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
