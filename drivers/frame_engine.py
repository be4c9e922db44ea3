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
3. overlapping valid candidates are resolved greedily, earliest first;
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


def greedy(starts: np.ndarray, length: int) -> np.ndarray:
    """Indices of non-overlapping frames (all ``length`` long), earliest first."""
    if starts.size < 2 or np.all(np.diff(starts) >= length):
        return np.arange(starts.size)
    keep, last_end = [], -1
    for i, s in enumerate(starts.tolist()):
        if s >= last_end:
            keep.append(i)
            last_end = s + length
    return np.asarray(keep, dtype=np.int64)


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

    def _candidates(self, b: np.ndarray) -> np.ndarray:
        n = b.size
        _, v0 = self.fixed[0]
        p = np.flatnonzero(b[:max(n - self.length + 1, 0)] == v0)   # complete frames only
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
        p = self._candidates(b)
        rows = rows_of(b, p, L)
        ok = self.check(rows) if p.size else np.zeros(0, bool)
        vi = np.flatnonzero(ok)
        acc = vi[greedy(p[vi], L)]
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
        elif rest >= L:                         # no frame can start this early any more
            drop = rest - (L - 1)
            if not self._pending:
                self._pending_header = self._starts_header(b, consumed)
            self._pending += drop
            consumed += drop
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


__all__ = ["FixedFrameStream", "FrameCounters", "affine_tables", "greedy", "rows_of", "xor_reduce_lookup"]
