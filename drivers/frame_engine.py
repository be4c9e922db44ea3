"""Vectorised decoding of fixed-length binary frames: the engine under the VectorNav binary
decoder (:mod:`rigctl.drivers.vectornav`) and the declarative frame driver
(:mod:`rigctl.drivers.frame_decl`).

A frame format is: its length ``L`` in bytes, a set of bytes fixed at known offsets (sync bytes,
a VectorNav group/field header, a length field with its one valid value), a vectorised check
(checksum / CRC over the frame rows) and a vectorised decode (rows -> named arrays). Over one
byte buffer ``b`` (numpy uint8), with no Python loop per frame:

1. candidates: every ``i`` where each fixed byte matches (``b[i + o] == v`` for all (o, v));
2. complete candidates (``i + L <= len(b)``) are checked in bulk on their (k, L) rows (a
   zero-copy view when they are back to back);
3. which valid candidates are frames: :func:`resolve` (a byte-wise parser's resynchronisation,
   independent of the read boundaries, that does not take a false frame over a good one);
4. bytes between accepted frames form garbage regions; a region of ``g`` bytes counts
   ``max(1, round(g / L))`` bad frames, or one truncated frame when it starts with the fixed
   header and ``g < L``. With byte substitution errors this equals the number of frames hit,
   since each hit frame leaves an ``L``-byte hole. Bytes before the first accepted frame of a
   stream that do not start with the header are ``presync_bytes`` (joining a running stream).

Checksums: :func:`affine_tables` turns any CRC/checksum that is affine over GF(2) (every CRC,
with any init and final XOR; XOR-8) into per-position lookup tables, so a whole block of frames
is checked with one gather and one XOR reduction (``crc(m) = c0 ^ XOR_j T[j, m_j]``).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view


@dataclass
class FrameCounters:
    """Running diagnostics of a frame stream; totals since creation."""

    frames: int = 0             # accepted frames
    bad_frames: int = 0         # frames lost to corruption (see the module docstring)
    truncated_frames: int = 0   # frames cut short (next header / end of stream)
    garbage_bytes: int = 0      # bytes not in any accepted frame (after the first one)
    presync_bytes: int = 0      # junk before the first accepted frame
    dropped_samples: int = 0    # counter / time-stamp gaps (filled in by the driver)
    out_of_order: int = 0       # frames whose counter / time did not advance (driver)


def affine_tables(func: Callable[[bytes], int], length: int, dtype=np.uint32) -> tuple[np.ndarray, int]:
    """Per-position tables ``T`` (length, 256) and constant ``c0`` with
    ``func(m) == c0 ^ XOR_j T[j, m[j]]`` for every message ``m`` of ``length`` bytes, valid
    for any ``func`` affine over GF(2) (CRCs with any init / final XOR, XOR-8). Built from
    8 * length + 1 calls of ``func``."""
    zero = bytes(length)
    c0 = int(func(zero))
    basis = np.zeros((length, 8), dtype=np.uint64)
    for j in range(length):
        for k in range(8):
            m = bytearray(length)
            m[j] = 1 << k
            basis[j, k] = int(func(bytes(m))) ^ c0
    v = np.arange(256)
    bits = ((v[:, None] >> np.arange(8)) & 1).astype(bool)       # (256, 8)
    table = np.zeros((length, 256), dtype=np.uint64)
    for k in range(8):
        table ^= np.where(bits[None, :, k], basis[:, k:k + 1], np.uint64(0))
    return table.astype(dtype), c0


def xor_reduce_lookup(table: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """XOR over j of ``table[j, cols[:, j]]`` for (k, m) uint8 ``cols``: (k,). One 256-entry
    lookup per column (cache-resident), which beats one gather over the whole block."""
    k, m = cols.shape
    acc = np.zeros(k, dtype=table.dtype)
    for j in range(m):
        acc ^= table[j][cols[:, j]]
    return acc


def rows_of(b: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """(k, length) bytes of the frames at ``starts``: a zero-copy view when back to back."""
    k = starts.size
    if not k:
        return np.empty((0, length), np.uint8)
    s0 = int(starts[0])
    if int(starts[-1]) - s0 == (k - 1) * length and (k < 3 or bool(np.all(np.diff(starts) == length))):
        return b[s0:s0 + k * length].reshape(k, length)
    return sliding_window_view(b, length)[starts]


#: how many rejected frames in a row a claimed length may be followed through (:func:`resolve`)
MAX_LINKS = 8


def resolve(starts: np.ndarray, ends: np.ndarray, valid: np.ndarray, n: int, *, final: bool,
            header_len: int, anchored: bool, layout: np.ndarray | None = None,
            seen: set[int] | None = None) -> tuple[np.ndarray, int]:
    """Which frame candidates of a buffer of ``n`` bytes are frames, as a byte-wise parser that
    resynchronises on the byte after a rejected preamble would take them -- whatever the read
    boundaries -- and without losing a good frame to a false one whose check passed by chance.

    ``starts`` (sorted): every position where a frame header begins (``header_len`` bytes
    matched); ``ends``: the end each one claims (-1: not known yet, the header is incomplete;
    -2: an impossible length); ``valid``: complete and passing the check (and structure).
    ``anchored``: byte 0 follows an accepted frame. A candidate not complete (and not
    ``final``) is undecided. A frame is *anchored* when it starts where the previous accepted
    frame ended or a header begins where it ends (a good frame in a stream is both; a false one,
    data that happen to hold a header and pass an 8- or 16-bit check, neither, but by chance).

    From the end of the last accepted frame:

    1. a rejected frame there whose claimed end (followed through at most :data:`MAX_LINKS`
       rejected frames) is an anchored valid frame, with no anchored valid frame inside the
       claim, had a corrupted payload: it is one lost frame, and nothing inside it is taken (a
       false frame in its data); a good frame inside the claim means the length was corrupted;
    2. else the next valid candidate is taken, unless it overlaps a later valid candidate, is not
       anchored, and one of those is: then it is the false one (it would cost a good frame);
    3. a data frame of a layout not seen before (``layout`` >= 0 not in ``seen``, when ``seen``
       holds any) is taken only when anchored at both ends: a length byte hit to a shorter length
       at an item boundary whose checksum passes by chance is the head of a corrupted frame, not
       a frame of a new layout (``seen`` gets the layouts of the frames taken);
    4. a decision that needs bytes not yet there (an undecided candidate first or in the way, an
       anchor not yet known) waits: nothing from there on is taken before them.

    Returns (indices of the accepted candidates, ``hold``: the first byte any decision still
    waits for, ``n`` if none; bytes before it that are in no frame may be discarded).
    The common case (valid candidates that do not overlap, nothing undecided before the last
    of them, no valid candidate inside a rejected frame's claim) is answered without a loop."""
    m = starts.size
    undecided = ~valid & ((ends == -1) | (ends > n)) if not final else np.zeros(m, bool)
    vi = np.flatnonzero(valid)
    vs, ve = starts[vi], ends[vi]
    und = np.flatnonzero(undecided)
    hold = int(starts[und[0]]) if und.size else n
    new_layouts: set[int] = set()
    if layout is not None:
        lv = layout[vi]
        lv = lv[lv >= 0]
        if lv.size:             # one layout (the usual stream) without a sort
            new_layouts = {int(lv[0])} if bool((lv == lv[0]).all()) else set(np.unique(lv).tolist())
        if not new_layouts <= (seen if seen else set(lv[:1].tolist())):
            return _resolve_slow(starts, ends, valid, undecided, n, final, header_len, anchored, layout, seen)
    if vi.size < 2 or bool(np.all(vs[1:] >= ve[:-1])):
        if not vi.size:
            return vi, hold
        if hold >= ve[-1]:
            inv = np.flatnonzero(~valid & ~undecided & (ends > 0))
            if not inv.size:
                if seen is not None:
                    seen.update(new_layouts)
                return vi, hold
            sh, eh = starts[inv], ends[inv]
            k = np.searchsorted(vs, sh, side="right")
            has = k < vi.size
            nxt = vs[np.minimum(k, vi.size - 1)]
            in_frame = (k > 0) & (sh < ve[np.maximum(k - 1, 0)])
            if not np.any(has & (nxt < eh) & ~in_frame):
                if seen is not None:
                    seen.update(new_layouts)
                return vi, hold
    return _resolve_slow(starts, ends, valid, undecided, n, final, header_len, anchored, layout, seen)


def _resolve_slow(starts, ends, valid, undecided, n, final, header_len, anchored, layout=None,
                  seen=None) -> tuple[np.ndarray, int]:
    """:func:`resolve` candidate by candidate."""
    s, e = starts.tolist(), ends.tolist()
    lay = layout.tolist() if layout is not None else [-1] * len(s)
    seen = seen if seen is not None else set()
    ok, und = valid.tolist(), undecided.tolist()
    m = len(s)
    at = {x: i for i, x in enumerate(s)}

    def header_at(x: int) -> bool | None:
        """Does a frame header begin at ``x`` (None: not known yet)?"""
        if x in at:
            return True
        if x + header_len > n:
            return x == n if final else None
        return False

    acc: list[int] = []
    last, anch, i = 0, anchored, 0
    new_last = True
    while True:
        if new_last and anch and last in at and not ok[at[last]]:
            h = at[last]
            if und[h]:
                return np.asarray(acc, np.int64), last
            x, target, links = e[h], None, 0
            while x > 0 and links <= MAX_LINKS:
                j = at.get(x)
                if j is None:
                    target = "wait" if header_at(x) is None else None
                    break
                if und[j]:
                    target = "wait"
                    break
                if ok[j]:
                    f = header_at(e[j])
                    target = "wait" if f is None else (x if f else None)
                    break
                x, links = e[j], links + 1
            if target not in (None, "wait"):   # a good frame inside the claim: the length was hit
                inner = [header_at(e[j]) for j in range(h + 1, at[target]) if ok[j]]
                target = "wait" if None in inner else (None if any(inner) else target)
            if target == "wait":
                return np.asarray(acc, np.int64), last
            if target is not None:
                last = target
                i = at[target]
                continue
        new_last = False
        while i < m and (s[i] < last or not (ok[i] or und[i])):
            i += 1
        if i >= m:
            return np.asarray(acc, np.int64), n
        if und[i]:
            return np.asarray(acc, np.int64), s[i]
        c = i
        rivals = []
        j = c + 1
        while j < m and s[j] < e[c]:
            if ok[j] or und[j]:
                rivals.append(j)
            j += 1
        if rivals and not (anch and s[c] == last):
            mine = header_at(e[c])
            if mine is None:
                return np.asarray(acc, np.int64), s[c]
            if not mine:
                if any(und[j] for j in rivals):
                    return np.asarray(acc, np.int64), s[c]
                theirs = [header_at(e[j]) for j in rivals]
                if any(t is None for t in theirs):
                    return np.asarray(acc, np.int64), s[c]
                if any(theirs):
                    i = c + 1               # the false one: rescan from the byte after its header
                    continue
        if lay[c] >= 0 and seen and lay[c] not in seen:
            fwd = header_at(e[c])
            if fwd is None:
                return np.asarray(acc, np.int64), s[c]
            if not (fwd and anch and s[c] == last):
                i = c + 1                   # a new layout next to garbage: a corrupted length
                continue
        acc.append(c)
        if lay[c] >= 0:
            seen.add(lay[c])
        last, anch, new_last = e[c], True, True
        i = c + 1


class FixedFrameStream:
    """Streaming decoder of fixed-length frames: ``feed(bytes) -> dict`` of decoded arrays (one
    row per accepted frame, plus ``offset``: the frame's byte offset in the stream); ``flush()``
    at the end of the stream. ``fixed``: [(offset, byte value)] every frame carries (the first
    one is the first sync byte, offset 0); ``check(rows) -> bool (k,)``; ``decode(rows) -> dict``."""

    def __init__(self, length: int, fixed: list[tuple[int, int]],
                 check: Callable[[np.ndarray], np.ndarray],
                 decode: Callable[[np.ndarray], dict[str, np.ndarray]]) -> None:
        if not fixed or fixed[0][0] != 0:
            raise ValueError("the first fixed byte must be at offset 0 (the sync byte)")
        self.length, self.fixed, self.check, self.decode = int(length), list(fixed), check, decode
        self.counters = FrameCounters()
        self._tail = np.empty(0, dtype=np.uint8)
        self._pending = 0               # bytes already discarded from the currently open region
        self._pending_header = False
        self._synced = False
        self._abs = 0
        self._header_len = max(o for o, _ in self.fixed) + 1
        self._at_frame_end = False      # the retained tail starts right after an accepted frame

    def _candidates(self, b: np.ndarray) -> np.ndarray:
        """Every position where the whole fixed header matches (complete frame or not)."""
        n = b.size
        _, v0 = self.fixed[0]
        p = np.flatnonzero(b[:max(n - self._header_len + 1, 0)] == v0)
        if len(self.fixed) > 1 and p.size:
            ok = np.ones(p.size, dtype=bool)
            for o, v in self.fixed[1:]:
                ok &= b[p + o] == v
            p = p[ok]
        return p

    def _starts_header(self, b: np.ndarray, i: int) -> bool:
        """Do the bytes at ``i`` match the fixed header (as far as they go)?"""
        n = b.size
        return all(i + o >= n or b[i + o] == v for o, v in self.fixed)

    def _account(self, g: int, header: bool, synced: bool) -> None:
        c = self.counters
        if g <= 0:
            return
        if not synced and not header:
            c.presync_bytes += g
            return
        c.garbage_bytes += g
        if header and g < self.length:
            c.truncated_frames += 1
        else:
            c.bad_frames += max(1, int(round(g / self.length)))

    def feed(self, data, final: bool = False) -> dict[str, np.ndarray]:
        new = data if isinstance(data, np.ndarray) else np.frombuffer(data, dtype=np.uint8)
        b = np.concatenate((self._tail, new)) if self._tail.size else new
        n, L = b.size, self.length
        p_all = self._candidates(b)
        ends = p_all + L
        complete = ends <= n
        p = p_all[complete]
        rows = rows_of(b, p, L)
        valid = np.zeros(p_all.size, dtype=bool)
        valid[complete] = self.check(rows) if p.size else False
        acc_all, hold = resolve(p_all, ends, valid, n, final=final, header_len=self._header_len,
                                anchored=self._at_frame_end)
        acc = np.searchsorted(p, p_all[acc_all])        # accepted frames among the complete ones
        a_start = p[acc]
        a_end = a_start + L
        prev_end = np.concatenate(([0], a_end[:-1]))
        gaps = a_start - prev_end
        for k in np.flatnonzero(gaps > 0).tolist():
            g0 = int(prev_end[k])
            hd = self._starts_header(b, g0)
            extra = 0
            if k == 0 and self._pending:
                hd, extra = self._pending_header, self._pending
                self._pending = 0
            self._account(int(gaps[k]) + extra, hd, self._synced or k > 0)
        if acc.size:
            if gaps[0] <= 0 and self._pending:
                self._account(self._pending, self._pending_header, self._synced)
                self._pending = 0
            self._synced = True
        consumed = int(a_end[-1]) if acc.size else 0
        rest = n - consumed
        if final:
            if rest or self._pending:
                hd = self._pending_header if self._pending else self._starts_header(b, consumed)
                self._account(rest + self._pending, hd, self._synced)
            self._pending, consumed = 0, n
        elif rest >= L and hold > consumed:     # no frame can start this early any more
            drop = min(rest - (L - 1), hold - consumed)
            if not self._pending:
                self._pending_header = self._starts_header(b, consumed)
            self._pending += drop
            consumed += drop
        self._at_frame_end = bool(acc.size and consumed == int(a_end[-1])) or (
            not acc.size and self._at_frame_end and consumed == 0)
        self._tail = b[consumed:].copy()
        if acc.size == rows.shape[0]:
            good = rows
        else:
            good = rows[acc] if rows.shape[0] else rows
        out = self.decode(good) if acc.size else self.decode(np.empty((0, L), np.uint8))
        out["offset"] = a_start + self._abs
        self._abs += consumed
        self.counters.frames += int(acc.size)
        return out

    def flush(self) -> dict[str, np.ndarray]:
        return self.feed(np.empty(0, np.uint8), final=True)


__all__ = ["FixedFrameStream", "FrameCounters", "MAX_LINKS", "affine_tables", "resolve", "rows_of",
           "xor_reduce_lookup"]
