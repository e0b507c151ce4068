"""A mapping with at most N values in memory and the rest, keys included, in an on-disk index.

The cloud keeps state for every pass it has ever seen (a recalibration months later must retract a
pass's segments exactly; a duplicate must be recognised as one). Held in Python objects, that state
grows with the passes; here it grows on disk. What stays in memory is the ``max_resident`` most
recently written (or, with ``promote``, read) values and their places in the iteration order;
every other key, its place, an integer ``tag`` (what a caller needs to know about a value without
decoding it) and its encoded value are a row of an SQLite table. SQLite, not an Arrow file: the
index is keyed random access with updates and deletes, and its page cache is bounded (``CACHE_KIB``).

A key gets its row when its value first leaves memory, not when it is written: until the resident
bound is reached the map costs what a dict costs (the cloud's ingest writes three maps per
segment; a row per write would be a large share of its CPU), and after that each write of a new key costs
the one spill it causes (spilled in groups, one transaction each: :data:`SPILL_GROUP`), plus an indexed
lookup (is it a spilled key?) only if a fixed-size filter of the keys that have rows says it may be one
(:data:`FILTER_BITS`).

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
#: Bits of a map's filter of the keys that have a row: a Bloom filter with two probes, of fixed size
#: (1 MiB, made when the first row is), so memory does not grow with the keys. Most keys written
#: are new, and a key the filter has not seen needs no lookup on disk; a key whose row was deleted
#: stays in it, costing only a lookup. False positives: ~0.05 % at 100 000 rows, ~4 % at 10⁶.
FILTER_BITS = 1 << 23
_FILTER_MASK = FILTER_BITS - 1
_BATCH = 64  # rows per read while iterating (spilled segments: ~0.5 MB)
_KEY_TEXT = json.JSONEncoder(separators=(",", ":")).encode  # one encoder (json.dumps builds one per call)
#: Most values spilled together, in one transaction: SQLite's cost of a row is mostly that of its
#: statement and commit, not its bytes, so a group of rows costs little more than one. A map spills
#: a group when it passes its bound, down to a group below it: memory stays within the bound. Maps of
#: fewer than ``SPILL_GROUP * SPILL_GROUP_SHARE`` values spill fewer at a time (one, when small).
SPILL_GROUP = 32
SPILL_GROUP_SHARE = 64
_INSERT = "INSERT INTO m (ord, k, tag, v) VALUES (?, ?, ?, ?)"
_UPDATE = "UPDATE m SET tag = ?, v = ? WHERE ord = ?"


def _key_text(key) -> str:
    return _KEY_TEXT(key)


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
                 tag: Callable[[object], int] | None = None, promote: bool = False, prefix: str = "spill-",
                 spill_group: int | None = None):
        if max_resident is not None and max_resident < 1:
            raise ValueError(f"max_resident: expected >= 1 or None, got {max_resident}")
        if spill_group is None:
            spill_group = max(1, min(SPILL_GROUP, (max_resident or 0) // SPILL_GROUP_SHARE))
        if max_resident is not None and not 1 <= spill_group <= max_resident:
            raise ValueError(f"spill_group: expected 1 to max_resident ({max_resident}), got {spill_group}")
        self.max_resident = max_resident
        self.spill_group = spill_group  # values spilled at once (see SPILL_GROUP)
        self._encode, self._decode, self._tag, self._promote = encode, decode, tag, promote
        self._spill_dir = Path(spill_dir) if spill_dir is not None else None
        self._prefix = prefix
        # Resident values, least recently written first (the next to spill).
        self._hot: collections.OrderedDict = collections.OrderedDict()
        # Each resident key's place in the iteration order (a spilled key's is in its row).
        self._ord: dict = {}
        self._next_ord = 0
        # Resident keys that have a row too (spilled once and back, or flushed): the row keeps their
        # place; it is rewritten, not inserted, when they spill again.
        self._rowed: set = set()
        # Resident keys whose row already holds their value encoded (:meth:`flush`): spilling them,
        # or a snapshot reading them, needs no encoding. Never with ``promote`` (a caller may change
        # a value it read without writing it back). A subset of ``_rowed``.
        self._clean: set = set()
        self._db: sqlite3.Connection | None = None
        # The last key looked up on disk and not found there: a write of it (``x in m`` then
        # ``m[x] = v``, ``m.get(x)`` then ``m[x] = v``: the callers' usual pattern) needs no second lookup.
        self._absent = _MISSING
        self._filter: bytearray | None = None  # keys that have a row (see FILTER_BITS)
        self._n = 0  # keys in all
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
            # 16 kB pages: a spilled segment (~7 kB) shares a page instead of spilling into overflow pages.
            for pragma in ("page_size=16384", "journal_mode=OFF", "synchronous=OFF", "locking_mode=EXCLUSIVE",
                           "temp_store=MEMORY", f"cache_size=-{CACHE_KIB}"):
                db.execute(f"PRAGMA {pragma}")
            # ``ord`` (the rowid) is the key's place in the iteration order, given when it was first written.
            db.execute("CREATE TABLE m (ord INTEGER PRIMARY KEY, k TEXT NOT NULL UNIQUE, tag INTEGER, v BLOB)")
            os.unlink(path)
            self._db = db
        return self._db

    @property
    def _any_spilled(self) -> bool:
        return self._n > len(self._hot)

    def _write(self, key, value) -> None:
        """The key's row holds ``value`` (inserted with the key's place if it has none yet)."""
        statement, row = self._row(key, value, self._ord[key])
        self._index().execute(statement, row)

    def _row(self, key, value, ordinal: int) -> tuple[str, tuple]:
        """The statement (and its parameters) that makes the key's row hold ``value``."""
        tag = self._tag(value) if self._tag is not None else None
        if key in self._rowed:
            return _UPDATE, (tag, self.encode_entry(key, value), ordinal)
        self._rowed.add(key)
        if self._filter is None:
            self._filter = bytearray(FILTER_BITS // 8)
        h = hash(key)
        for bit in (h & _FILTER_MASK, (h >> 23) & _FILTER_MASK):
            self._filter[bit >> 3] |= 1 << (bit & 7)
        return _INSERT, (ordinal, _key_text(key), tag, self.encode_entry(key, value))

    def _may_have_row(self, key) -> bool:
        """False if ``key`` has never had a row (the filter); True if it may have one."""
        f = self._filter
        if f is None:
            return False
        h = hash(key)
        a, b = h & _FILTER_MASK, (h >> 23) & _FILTER_MASK
        return bool(f[a >> 3] >> (a & 7) & 1 and f[b >> 3] >> (b & 7) & 1)

    def _spill_oldest(self, n: int) -> None:
        """The ``n`` oldest resident values out to their rows, in one transaction."""
        hot, rows = self._hot, {_INSERT: [], _UPDATE: []}
        for _ in range(n):
            key, value = hot.popitem(last=False)
            ordinal = self._ord.pop(key)
            if key not in self._clean:
                statement, row = self._row(key, value, ordinal)
                rows[statement].append(row)
            self._clean.discard(key)
            self._rowed.discard(key)
            self.spilled_total += 1
        if rows[_INSERT] or rows[_UPDATE]:
            db = self._index()
            db.execute("BEGIN")
            try:
                for statement, params in rows.items():
                    if params:
                        db.executemany(statement, params)
            finally:
                db.execute("COMMIT")

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

    def _cold(self, key, columns: str = "v") -> tuple | None:
        """A spilled key's row (``columns`` of it), None if the key is not spilled."""
        if self._db is None or not self._any_spilled:
            return None
        if not self._may_have_row(key):
            self._absent = key
            return None
        row = self._db.execute(f"SELECT {columns} FROM m WHERE k = ?", (_key_text(key),)).fetchone()
        if row is None:
            self._absent = key
        return row

    # -- mapping -------------------------------------------------------------------------------
    def __getitem__(self, key):
        try:
            return self._hot[key]
        except KeyError:
            pass
        if self.max_resident is None:
            raise KeyError(key)
        row = self._cold(key, "ord, v")
        if row is None:
            raise KeyError(key)
        value = self.decode_entry(key, row[1])
        self.reads += 1
        if self._promote:  # its row keeps a stale copy, rewritten when it spills again
            self._hot[key] = value
            self._ord[key] = row[0]
            self._rowed.add(key)
            self._trim()
        return value

    def get(self, key, default=None):
        """``self[key]`` if present, else ``default`` (a resident key without the mapping's detour
        through an exception: the ingest path asks for a pass's state per segment)."""
        value = self._hot.get(key, _MISSING)
        if value is not _MISSING:
            return value
        try:
            return self[key]
        except KeyError:
            return default

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
            # A spilled key written again keeps its place. (Only a write makes a key present, so
            # one just found absent still is.)
            row = None if key == self._absent else self._cold(key, "ord")
            self._absent = _MISSING
            if row is None:
                self._ord[key] = self._next_ord
                self._next_ord += 1
                self._n += 1
            else:
                self._ord[key] = row[0]
                self._rowed.add(key)
            hot[key] = value
        self._trim()

    def _trim(self) -> None:
        over = len(self._hot) - self.max_resident
        if over > 0:  # down to a group below the bound: the next group spills together
            self._spill_oldest(min(over + self.spill_group - 1, len(self._hot)))

    def __delitem__(self, key) -> None:
        if self.max_resident is None:
            if self._hot.pop(key, _MISSING) is _MISSING:
                raise KeyError(key)
            self._n -= 1
            return
        if self._hot.pop(key, _MISSING) is not _MISSING:
            ordinal = self._ord.pop(key)
            self._clean.discard(key)
            if key in self._rowed:
                self._rowed.discard(key)
                self._db.execute("DELETE FROM m WHERE ord = ?", (ordinal,))
            self._n -= 1
            return
        if self._db is None or not self._any_spilled or not self._may_have_row(key):
            raise KeyError(key)
        if not self._db.execute("DELETE FROM m WHERE k = ?", (_key_text(key),)).rowcount:
            raise KeyError(key)
        self._n -= 1

    def __contains__(self, key) -> bool:
        return key in self._hot or self._cold(key, "1") is not None

    def __len__(self) -> int:
        return self._n

    def _rows(self, columns: str) -> Iterator[tuple]:
        """``(ord, k, …)`` rows in order, read in batches (the caller may read the map in between)."""
        if self._db is None:
            return
        last = -1
        while True:
            rows = self._db.execute(f"SELECT ord, k{columns} FROM m WHERE ord > ? ORDER BY ord LIMIT ?",
                                    (last, _BATCH)).fetchall()
            if not rows:
                return
            yield from rows
            last = rows[-1][0]

    def _walk(self, columns: str) -> Iterator[tuple]:
        """``(key, value or _MISSING, row or None)`` for every key in order: the resident keys (as
        they were when the walk began, by their places) merged with the rows. A resident key that
        has a row comes with it; one spilled meanwhile comes without (its row is read if wanted)."""
        resident = sorted((o, k) for k, o in self._ord.items())
        i = 0
        for row in self._rows(columns):
            o = row[0]
            while i < len(resident) and resident[i][0] < o:
                key = resident[i][1]
                i += 1
                yield key, self._hot.get(key, _MISSING), None
            if i < len(resident) and resident[i][0] == o:
                key = resident[i][1]
                i += 1
                value = self._hot.get(key, _MISSING)
                # Its row was read while it was resident: current only if it still is (and clean).
                yield key, value, row if value is not _MISSING else None
                continue
            key = _key_of(row[1])
            yield key, self._hot.get(key, _MISSING), row
        for _, key in resident[i:]:
            yield key, self._hot.get(key, _MISSING), None

    def __iter__(self) -> Iterator:
        if self.max_resident is None:
            yield from self._hot
            return
        for key, value, row in self._walk(""):
            if value is not _MISSING or row is not None or key in self:
                yield key

    def items(self) -> Iterator[tuple]:  # type: ignore[override]
        """``(key, value)`` in order; spilled values are decoded copies (not brought into memory)."""
        if self.max_resident is None:
            yield from self._hot.items()
            return
        for key, value, row in self._walk(", v"):
            if value is _MISSING:
                blob = row[2] if row is not None else (self._cold(key) or (None,))[0]
                if blob is None:  # deleted while walking
                    continue
                value = self.decode_entry(key, blob)
                self.reads += 1
            yield key, value

    def values(self) -> Iterator:  # type: ignore[override]
        return (v for _, v in self.items())

    # -- beyond a dict -------------------------------------------------------------------------
    def encode_entry(self, key, value) -> bytes:
        """What ``key``'s row holds for ``value`` (the ``encode`` given; a subclass may write less
        for a value kept elsewhere, and read it back in :meth:`decode_entry`)."""
        return self._encode(value)

    def decode_entry(self, key, blob: bytes):
        """``key``'s value from what its row holds (the inverse of :meth:`encode_entry`)."""
        return self._decode(blob)

    def peek(self, key):
        """The value if it is in memory (no read), else None."""
        return self._hot.get(key)

    def tag_of(self, key) -> int:
        """The value's tag, without decoding a spilled value."""
        value = self._hot.get(key, _MISSING)
        if value is not _MISSING:
            return self._tag(value)
        row = self._cold(key, "tag")
        if row is None:
            raise KeyError(key)
        return row[0]

    def encoded(self) -> Iterator[tuple]:
        """``(key, encoded value)`` in order, without decoding spilled values (e.g. a snapshot)."""
        if self.max_resident is None:
            for key, value in list(self._hot.items()):
                yield key, self.encode_entry(key, value)
            return
        for key, value, row in self._walk(", v"):
            if row is not None and (value is _MISSING or key in self._clean):
                yield key, row[2]
            elif value is not _MISSING:
                yield key, self.encode_entry(key, value)
            else:
                blob = self._cold(key)
                if blob is not None:
                    yield key, blob[0]

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
