"""A mapping with at most N values in memory and the rest, keys included, in an on-disk index.

The cloud keeps state for every pass it has ever seen (a recalibration months later must retract a
pass's segments exactly; a duplicate must be recognised as one). Held in Python objects, that state
grows with the passes; here it grows on disk. What stays in memory is the ``max_resident`` most
recently written (or, with ``promote``, read) values; every key, its place in the iteration order,
an integer ``tag`` (what a caller needs to know about a value without decoding it) and the encoded
values beyond the window are rows of an SQLite table. SQLite, not an Arrow file: the index is keyed
random access with updates and deletes, and its page cache is bounded (``CACHE_KIB``).

Semantics are a ``dict``'s: iteration follows first insertion (a write to an existing key keeps
its place; a key deleted and written again goes last), so anything summed over the values sums in
the same order whether they are resident or not. With ``max_resident=None`` it *is* a dict: no
disk at all.

The file belongs to one process lifetime: created in ``spill_dir`` and unlinked at once (a killed
process leaves nothing behind; a restarted cloud rebuilds its state from its journal). SQLite runs
without a rollback journal or fsync for the same reason.
"""

from __future__ import annotations

import collections
import json
import os
import sqlite3
import tempfile
import time
from collections.abc import Callable, Iterator, MutableMapping
from pathlib import Path

CACHE_KIB = 256  # SQLite page cache per map (fills within minutes: no slow creep of RSS)
_BATCH = 64  # rows per read while iterating (spilled segments: ~0.5 MB)


def _key_text(key) -> str:
    return json.dumps(key, separators=(",", ":"))


def _key_of(text: str):
    k = json.loads(text)
    return tuple(k) if isinstance(k, list) else k


class SpillMap(MutableMapping):
    """``key → value``; keys are str/int or flat tuples of them (they are stored as JSON).

    ``encode``/``decode``: value ↔ bytes (exact); ``tag``: an int per value kept beside it
    (:meth:`tag_of` answers without decoding); ``promote``: a read of a spilled value brings it back
    into memory (so a caller may mutate what it got, as with a dict) instead of decoding a copy.
    """

    def __init__(self, max_resident: int | None, spill_dir: str | Path | None,
                 encode: Callable[[object], bytes], decode: Callable[[bytes], object],
                 tag: Callable[[object], int] | None = None, promote: bool = False, prefix: str = "spill-"):
        if max_resident is not None and max_resident < 1:
            raise ValueError(f"max_resident: expected >= 1 or None, got {max_resident}")
        self.max_resident = max_resident
        self._encode, self._decode, self._tag, self._promote = encode, decode, tag, promote
        self._spill_dir = Path(spill_dir) if spill_dir is not None else None
        self._prefix = prefix
        # Resident values, least recently written first (the next to spill).
        self._hot: collections.OrderedDict = collections.OrderedDict()
        # Resident keys whose row already holds their value encoded (:meth:`flush`): spilling them,
        # or a snapshot reading them, needs no encoding. Never with ``promote`` (a caller may change
        # a value it read without writing it back).
        self._clean: set = set()
        self._db: sqlite3.Connection | None = None
        self._n = 0  # keys in all (bounded: rows of the index)
        self.spilled_total = 0  # values written out over the map's life
        self.reads = 0  # spilled values decoded back

    # -- the index -----------------------------------------------------------------------------
    def _index(self) -> sqlite3.Connection:
        if self._db is None:
            if self._spill_dir is not None:
                self._spill_dir.mkdir(parents=True, exist_ok=True)
            fd, path = tempfile.mkstemp(prefix=self._prefix, suffix=".sqlite", dir=self._spill_dir)
            os.close(fd)
            db = sqlite3.connect(path, isolation_level=None, check_same_thread=False)
            # No rollback journal and no temporary files: the database is the only file, so it can be
            # unlinked while open (anonymous, gone with the process); no fsync (never read again).
            # 16 kB pages: a spilled segment (~4 kB) takes a quarter page, not two 4 kB pages (overflow).
            for pragma in ("page_size=16384", "journal_mode=OFF", "synchronous=OFF", "locking_mode=EXCLUSIVE",
                           "temp_store=MEMORY", f"cache_size=-{CACHE_KIB}"):
                db.execute(f"PRAGMA {pragma}")
            # ``ord`` (the rowid) is the iteration order: a new key gets max+1, i.e. goes last.
            db.execute("CREATE TABLE m (ord INTEGER PRIMARY KEY, k TEXT NOT NULL UNIQUE, tag INTEGER, v BLOB)")
            os.unlink(path)
            self._db = db
        return self._db

    def _write(self, key, value) -> None:
        tag = self._tag(value) if self._tag is not None else None
        self._index().execute("UPDATE m SET tag = ?, v = ? WHERE k = ?", (tag, self._encode(value), _key_text(key)))

    def _spill_oldest(self) -> None:
        key, value = self._hot.popitem(last=False)
        if key in self._clean:
            self._clean.discard(key)
        else:
            self._write(key, value)
        self.spilled_total += 1

    def flush(self, budget_s: float) -> int:
        """Write resident values to their rows ahead of time, oldest first, for at most about
        ``budget_s`` (the daemon calls it when the bus is quiet): the encoding work a spill or a
        snapshot would do under load is done while idle. Returns how many were written."""
        if self.max_resident is None or self._promote:
            return 0
        t_end = time.monotonic() + budget_s
        n = 0
        for key, value in self._hot.items():
            if key in self._clean:
                continue
            if n and time.monotonic() >= t_end:
                break
            self._write(key, value)
            self._clean.add(key)
            n += 1
        return n

    def _cold(self, key) -> bytes | None:
        row = self._index().execute("SELECT v FROM m WHERE k = ?", (_key_text(key),)).fetchone() \
            if self._db is not None else None
        return None if row is None else row[0]

    # -- mapping -------------------------------------------------------------------------------
    def __getitem__(self, key):
        try:
            return self._hot[key]
        except KeyError:
            pass
        if self.max_resident is None:
            raise KeyError(key)
        blob = self._cold(key)
        if blob is None:
            raise KeyError(key)
        value = self._decode(blob)
        self.reads += 1
        if self._promote:
            self._hot[key] = value  # its row keeps a stale copy, rewritten when it spills again
            self._trim()
        return value

    def __setitem__(self, key, value) -> None:
        hot = self._hot
        if self.max_resident is None:
            self._n += key not in hot
            hot[key] = value  # a dict: an existing key keeps its place
            return
        if key in hot:
            hot[key] = value
            hot.move_to_end(key)
            self._clean.discard(key)
        else:
            cur = self._index().execute("INSERT OR IGNORE INTO m (k) VALUES (?)", (_key_text(key),))
            self._n += cur.rowcount
            hot[key] = value
        self._trim()

    def _trim(self) -> None:
        while len(self._hot) > self.max_resident:
            self._spill_oldest()

    def __delitem__(self, key) -> None:
        was_hot = self._hot.pop(key, _MISSING) is not _MISSING
        self._clean.discard(key)
        if self.max_resident is None:
            if not was_hot:
                raise KeyError(key)
            self._n -= 1
            return
        if self._db is None:  # nothing was ever written: a key not resident is not here
            raise KeyError(key)
        if self._db.execute("DELETE FROM m WHERE k = ?", (_key_text(key),)).rowcount:
            self._n -= 1
        elif not was_hot:
            raise KeyError(key)

    def __contains__(self, key) -> bool:
        if key in self._hot:
            return True
        if self._db is None:
            return False
        return self._db.execute("SELECT 1 FROM m WHERE k = ?", (_key_text(key),)).fetchone() is not None

    def __len__(self) -> int:
        return self._n

    def _rows(self, columns: str) -> Iterator[tuple]:
        """``(ord, k, …)`` rows in order, read in batches (the caller may read the map in between)."""
        last = -1
        while True:
            rows = self._db.execute(f"SELECT ord, k{columns} FROM m WHERE ord > ? ORDER BY ord LIMIT ?",
                                    (last, _BATCH)).fetchall()
            if not rows:
                return
            yield from rows
            last = rows[-1][0]

    def __iter__(self) -> Iterator:
        if self._db is None:
            yield from list(self._hot) if self.max_resident is not None else self._hot
            return
        for _, k in self._rows(""):
            yield _key_of(k)

    def items(self) -> Iterator[tuple]:  # type: ignore[override]
        """``(key, value)`` in order; spilled values are decoded copies (not brought into memory)."""
        if self._db is None:
            yield from (list(self._hot.items()) if self.max_resident is not None else self._hot.items())
            return
        for _, k, v in self._rows(", v"):
            key = _key_of(k)
            value = self._hot.get(key, _MISSING)
            if value is _MISSING:
                value = self._decode(v)
                self.reads += 1
            yield key, value

    def values(self) -> Iterator:  # type: ignore[override]
        return (v for _, v in self.items())

    # -- beyond a dict -------------------------------------------------------------------------
    def peek(self, key):
        """The value if it is in memory (no read), else None."""
        return self._hot.get(key)

    def tag_of(self, key) -> int:
        """The value's tag, without decoding a spilled value."""
        value = self._hot.get(key, _MISSING)
        if value is not _MISSING:
            return self._tag(value)
        row = self._db.execute("SELECT tag FROM m WHERE k = ?", (_key_text(key),)).fetchone() \
            if self._db is not None else None
        if row is None:
            raise KeyError(key)
        return row[0]

    def encoded(self) -> Iterator[tuple]:
        """``(key, encoded value)`` in order, without decoding spilled values (e.g. a snapshot)."""
        if self._db is None:
            for key, value in list(self._hot.items()):
                yield key, self._encode(value)
            return
        for _, k, v in self._rows(", v"):
            key = _key_of(k)
            value = self._hot.get(key, _MISSING)
            yield key, (v if value is _MISSING or key in self._clean else self._encode(value))

    def resident_values(self):
        return self._hot.values()

    @property
    def resident(self) -> int:
        return len(self._hot)

    @property
    def spilled(self) -> int:
        return self._n - len(self._hot)

    def disk_bytes(self) -> int:
        """Size of the on-disk index (SQLite reuses the pages of deleted rows: it stays at the live size)."""
        if self._db is None:
            return 0
        (pages,) = self._db.execute("PRAGMA page_count").fetchone()
        (size,) = self._db.execute("PRAGMA page_size").fetchone()
        return int(pages) * int(size)

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None


_MISSING = object()
