"""SQLite content caches (``party.text.cache.PartTextCache``, ``party.text.store.EmbeddingCache``).

One setup for both: the parent folder is created, the database opened in WAL mode with
``synchronous=NORMAL`` (a commit survives a crash of the process; SQLite's journal keeps the
file consistent), the schema created if absent, and a file that is not a usable database
reported by name. Subclasses set ``schema`` (CREATE TABLE IF NOT EXISTS statements), ``kind``
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
        raise sqlite3.DatabaseError(f"{path}: not a usable {kind} ({e}){hint}") from e
    return db


def select_in(db: sqlite3.Connection, query: str, args: Sequence, keys: Sequence, chunk: int) -> Iterator[tuple]:
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
        self.db = connect(self.path, self.schema, self.kind, self.hint)

    def close(self) -> None:
        self.db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
