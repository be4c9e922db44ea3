"""Vectorised decoder for Xsens MT byte streams (MTData2 plus control messages).

Algorithm over one byte buffer ``b`` (numpy uint8), with no Python loop per frame:

1. candidates: every ``i`` with ``b[i] == 0xFA and b[i+1] == 0xFF``;
2. frame length from LEN (or the big-endian EXTLEN when LEN == 0xFF): ``n = 5 + LEN`` or ``7 + EXTLEN``;
3. checksum in bulk with a wrapping uint8 prefix sum ``S``: a frame at ``i`` of ``n`` bytes is
   valid iff ``(S[i+n-1] - S[i]) mod 256 == 0`` (sum of BID..CS);
4. MTData2 payloads are checked for structure (items must tile the payload exactly) once per
   distinct layout, then every frame of that length is compared against the layout's item
   headers in one vector comparison; frames that differ fall back to a per-frame parse;
5. which candidates are frames is decided by :func:`rigctl.drivers.frame_engine.resolve`: as a
   byte-wise parser resynchronising from the byte after a rejected preamble, whatever the read
   boundaries, and never taking a false frame in a payload (it passed the 8-bit checksum by
   chance) over the good frame it overlaps;
6. bytes between accepted frames form garbage regions. A region of ``g`` bytes next to frames of
   ``L`` bytes counts ``max(1, round(g / L))`` bad frames, or one truncated frame when it starts
   with a preamble and ``g < L``. With byte substitution errors this equals the number of frames
   hit exactly, since each hit frame leaves an ``L``-byte hole.

:class:`MTData2Stream` keeps the unconsumed tail between feeds, unwraps the u16 PacketCounter
(gaps -> ``dropped_samples``; a counter that does not advance is rejected and counted as
``out_of_order``) and the SampleTimeFine counter (10 kHz ticks, wrap configurable, default 2^32).
A SampleTimeFine that does not continue the last accepted one -- more than
:data:`MAX_TICKS_PER_COUNT` ticks per PacketCounter step ahead of it, or behind it (without a
counter: more than half the wrap either way) -- is not taken as the new reference: a corrupted
time that passed the checksum would otherwise make the next true one read as a wrap and put
every later sample 2^32 ticks (4.97 days) late. The frame is kept without a time
(``sample_time_fine`` -1, ``time_s`` NaN) and counted in ``time_outliers``; two such stamps in a
row that continue each other are a new time base (a restarted MTi, or a link loss longer than the
counter resolves), taken as the old decoder took it and counted in ``time_restarts``. One that
begins behind the last accepted stamp (within half the wrap) is a device restart (its
SampleTimeFine began again from 0: the MTi lost power), also counted in ``device_restarts`` --
the count rigctl's engine re-warms the IMU on (docs/daemon.md). A time base ahead of the last
stamp is not: a measurement paused longer than the counter steps account for (a slow
reconfiguration after a reconnect: SampleTimeFine runs on in config mode, PacketCounter does
not), or an outage longer than the counter resolves.
Unknown data IDs are counted per ID in ``unknown_xdi`` (the known items of such a frame are kept).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .frame_engine import resolve
from .xsens import (MAX_EXT_LEN, MAX_FRAME_BYTES, MID, PRECISION_BYTES, SAMPLE_TIME_FINE_HZ,
                    SAMPLE_TIME_FINE_WRAP, XDI_COMPONENTS, XDI_FIELD, XDI_INT_SIZE, Message,
                    Precision, item_size, split_xdi)

log = logging.getLogger(__name__)
RESYNC_RUN = 3  # consecutive in-sequence frames after which a counter jump is taken as a restart
#: the most SampleTimeFine may advance per PacketCounter step: 1 s, the packet period at 1 Hz,
#: the slowest whole-Hz output
MAX_TICKS_PER_COUNT = SAMPLE_TIME_FINE_HZ


@dataclass
class DecodeCounters:
    """Running diagnostics of a stream; all counts are totals since creation."""

    frames: int = 0             # accepted MTData2 frames
    messages: int = 0           # accepted other messages (acks, errors, ...)
    bad_frames: int = 0         # frames lost to corruption (see module docstring)
    truncated_frames: int = 0   # frames cut short by the next preamble / end of stream
    garbage_bytes: int = 0      # bytes not belonging to any accepted frame
    presync_bytes: int = 0      # junk before the first accepted frame (joining a running stream)
    malformed_frames: int = 0   # checksum valid, MTData2 structure invalid (also within bad_frames)
    dropped_samples: int = 0    # PacketCounter gaps
    out_of_order: int = 0       # frames rejected because the counter did not advance
    counter_restarts: int = 0   # counter resynchronised after a run of consistent frames
    frames_without_counter: int = 0
    time_outliers: int = 0      # SampleTimeFine not continuing the last accepted one: frame kept without a time
    time_restarts: int = 0      # SampleTimeFine took a new time base (two stamps in a row continuing each other)
    device_restarts: int = 0    # ... one that began behind the last accepted stamp: the MTi restarted
    unknown_xdi: dict[int, int] = field(default_factory=dict)


REAL_FIELDS = {"acceleration": 3, "rate_of_turn": 3, "delta_v": 3, "delta_q": 4, "temperature": 1}
INT_FIELDS = ("packet_counter", "sample_time_fine", "status_word")


@dataclass
class MTData2Batch:
    """Decoded samples, one row per accepted MTData2 frame (NaN / -1 where a frame lacks a field).

    counter: unwrapped PacketCounter (int64); sample_time_fine: unwrapped ticks of 1e-4 s;
    time_s: sample_time_fine / 10 kHz (s); acceleration m/s^2, rate_of_turn rad/s, delta_v m/s,
    delta_q (w,x,y,z), temperature degC, status_word u32; offsets: byte offset of each frame in
    the stream fed so far (diagnostics).
    """

    counter: np.ndarray
    sample_time_fine: np.ndarray
    time_s: np.ndarray
    acceleration: np.ndarray
    rate_of_turn: np.ndarray
    temperature: np.ndarray
    status_word: np.ndarray
    delta_v: np.ndarray
    delta_q: np.ndarray
    offsets: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))
    messages: list[Message] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.counter)


def _empty_fields(n: int) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {k: np.full(n, -1, dtype=np.int64) for k in INT_FIELDS}
    for k, m in REAL_FIELDS.items():
        out[k] = np.full((n, m) if m > 1 else n, np.nan)
    return out


def parse_layout(frame: bytes | np.ndarray, hdr: int) -> tuple[tuple[int, int, int], ...] | None:
    """Item layout ((xdi, data offset in frame, size), ...) of one MTData2 frame, None if malformed.

    Unknown XDIs are kept in the layout (decoded as nothing, counted by the caller); a known XDI
    with the wrong size makes the frame malformed.
    """
    end = len(frame) - 1
    pos, items = hdr, []
    while pos < end:
        if pos + 3 > end:
            return None
        xdi = (int(frame[pos]) << 8) | int(frame[pos + 1])
        size = int(frame[pos + 2])
        pos += 3
        if pos + size > end:
            return None
        expect = item_size(xdi)
        base = split_xdi(xdi)[0]
        if (base in XDI_FIELD or expect is not None) and expect != size:
            return None
        items.append((xdi, pos, size))
        pos += size
    return tuple(items)


def _decode_real(raw: np.ndarray, prec: int, k: int) -> np.ndarray:
    """(n, k*size) big-endian bytes -> (n, k) float64 at a precision."""
    n = raw.shape[0]
    raw = np.ascontiguousarray(raw)
    if prec == Precision.FLOAT32:
        return raw.view(">f4").reshape(n, k).astype(np.float64)
    if prec == Precision.FLOAT64:
        return raw.view(">f8").reshape(n, k).astype(np.float64)
    if prec == Precision.FP1220:
        return raw.view(">i4").reshape(n, k) / float(1 << 20)
    r = raw.reshape(n, k, 6)
    frac = np.ascontiguousarray(r[..., :4]).view(">u4")[..., 0].astype(np.float64)
    whole = np.ascontiguousarray(r[..., 4:]).view(">i2")[..., 0].astype(np.float64)
    return whole + frac / 2.0**32


def _find_candidates(b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate starts, total lengths (-1 = header incomplete) and header lengths."""
    n = b.size
    fa = np.flatnonzero(b[:-1] == 0xFA) if n > 1 else np.empty(0, np.int64)
    p = fa[b[fa + 1] == 0xFF]
    total = np.full(p.size, -1, dtype=np.int64)
    hdr = np.full(p.size, 4, dtype=np.int64)
    has_len = p + 4 <= n
    ln = np.zeros(p.size, dtype=np.int64)
    ln[has_len] = b[p[has_len] + 3]
    std = has_len & (ln != 0xFF)
    total[std] = ln[std] + 5
    ext = has_len & (ln == 0xFF) & (p + 6 <= n)
    if ext.any():
        pe = p[ext]
        el = (b[pe + 4].astype(np.int64) << 8) | b[pe + 5]
        tot = el + 7
        tot[el > MAX_EXT_LEN] = -2          # impossible length: never valid
        total[ext] = tot
        hdr[ext] = 6
    return p, total, hdr


def _rows(b: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """(k, length) bytes of the frames at ``starts``: a zero-copy view when they are back to back."""
    k = starts.size
    s0 = int(starts[0])
    if int(starts[-1]) - s0 == (k - 1) * length and (k < 3 or bool(np.all(np.diff(starts) == length))):
        return b[s0:s0 + k * length].reshape(k, length)
    return sliding_window_view(b, length)[starts]


class MTData2Stream:
    """Streaming decoder: ``feed(bytes) -> MTData2Batch``; ``flush()`` at end of stream."""

    def __init__(self, wrap_ticks: int = SAMPLE_TIME_FINE_WRAP) -> None:
        self.wrap_ticks = int(wrap_ticks)
        self.counters = DecodeCounters()
        self._tail = np.empty(0, dtype=np.uint8)
        self._pending = 0            # bytes already discarded from the currently open region
        self._pending_header = False
        self._synced = False
        self._ref_len = 0            # length of the last accepted MTData2 frame
        self._prev_counter: int | None = None   # unwrapped counter of the last accepted frame
        self._prev_raw: int = 0
        self._run = 0
        self._run_last = -1
        self._prev_stf: int | None = None   # unwrapped SampleTimeFine of the last accepted stamp
        self._prev_stf_raw = 0
        self._prev_stf_counter = -1          # its unwrapped PacketCounter (-1: none)
        self._stf_cand: tuple[int, int] | None = None  # (raw, counter) of the last rejected stamp
        self._abs = 0                # stream offset of the first byte of the retained tail
        self._at_frame_end = False   # the retained tail starts right after an accepted frame
        self._lengths: set[int] = set()     # lengths of the MTData2 frames accepted so far

    def reset_counters(self) -> None:
        """Forget counter/time history (call after the device re-enters measurement)."""
        self._prev_counter = None
        self._prev_stf = None
        self._stf_cand = None
        self._lengths.clear()       # a new measurement may bring a new output layout

    # ------------------------------------------------------------------ region accounting
    def _account_region(self, g: int, starts_with_header: bool, ref_len: int, synced: bool = True) -> None:
        c = self.counters
        if g <= 0:
            return
        if not synced and not starts_with_header:
            c.presync_bytes += g
            return
        c.garbage_bytes += g
        ref = ref_len if ref_len > 0 else g
        if starts_with_header and g < ref:
            c.truncated_frames += 1
        else:
            c.bad_frames += max(1, int(round(g / ref)))

    def feed(self, data: bytes | bytearray | memoryview | np.ndarray, final: bool = False) -> MTData2Batch:
        """Decode ``data`` appended to the retained tail; returns the frames completed by it."""
        new = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data
        b = np.concatenate((self._tail, new)) if self._tail.size else new
        n = b.size
        p, total, hdr = _find_candidates(b)
        complete = (total > 0) & (p + total <= n)
        pc, tc, hc = p[complete], total[complete], hdr[complete]
        mids = b[pc + 2]
        layout_id = np.full(pc.size, -1, dtype=np.int64)
        layouts: list[tuple] = []
        valid, is_d2, groups = self._check_groups(b, pc, tc, hc, mids, layout_id, layouts)
        malformed = is_d2 & (layout_id < 0)
        valid &= ~malformed
        ends = np.where(total > 0, p + total, total)      # -1: header incomplete, -2: impossible
        valid_all = np.zeros(p.size, dtype=bool)
        valid_all[complete] = valid
        layout = np.full(p.size, -1, dtype=np.int64)        # MTData2 frames: their length
        layout[complete] = np.where(is_d2 & valid, tc, -1)
        acc_all, hold = resolve(p, ends, valid_all, n, final=final, header_len=2,
                                anchored=self._at_frame_end, layout=layout, seen=self._lengths)
        acc = np.searchsorted(pc, p[acc_all])           # accepted frames among the complete ones
        a_start, a_end = pc[acc], pc[acc] + tc[acc]
        a_d2 = mids[acc] == MID.MTDATA2
        # ---- regions between accepted frames
        prev_end = np.concatenate(([0], a_end[:-1]))
        gaps = a_start - prev_end
        ref = tc[acc].copy()
        if ref.size and not a_d2.all():     # control messages do not define the frame size
            d2len = np.where(a_d2, ref, 0)
            idx = np.maximum.accumulate(np.where(a_d2, np.arange(ref.size), -1))
            ref = np.where(idx >= 0, d2len[np.maximum(idx, 0)], self._ref_len)
        for k in np.flatnonzero(gaps > 0).tolist():
            g0 = int(prev_end[k])
            hd = bool(b[g0] == 0xFA and g0 + 1 < n and b[g0 + 1] == 0xFF)
            if k == 0 and self._pending:
                hd = self._pending_header
            self._account_region(int(gaps[k]) + (self._pending if k == 0 else 0), hd, int(ref[k]),
                                 self._synced or k > 0)
            if k == 0:
                self._pending = 0
        if acc.size:
            if gaps[0] <= 0 and self._pending:
                self._account_region(self._pending, self._pending_header, int(ref[0]), self._synced)
                self._pending = 0
            self._synced = True
            if a_d2.any():
                self._ref_len = int(tc[acc][a_d2][-1])
        consumed = int(a_end[-1]) if acc.size else 0
        rest = n - consumed
        if final:
            if rest:
                hd = bool(b[consumed] == 0xFA and (consumed + 1 >= n or b[consumed + 1] == 0xFF))
                if self._pending:
                    hd = self._pending_header
                self._account_region(rest + self._pending, hd, self._ref_len, self._synced)
            self._pending, consumed = 0, n
        elif rest > MAX_FRAME_BYTES and hold > consumed:    # no frame can start this early any more
            drop = min(rest - MAX_FRAME_BYTES, hold - consumed)
            if not self._pending:
                self._pending_header = bool(b[consumed] == 0xFA and b[consumed + 1] == 0xFF)
            self._pending += drop
            consumed += drop
        self._at_frame_end = bool(acc.size and consumed == int(a_end[-1])) or (
            not acc.size and self._at_frame_end and consumed == 0)
        self._tail = b[consumed:].copy()
        # malformed frames outside accepted frames and inside the consumed part are real events
        self.counters.malformed_frames += self._count_free(pc, tc, malformed & (pc < consumed), acc)
        msgs = [Message(mid=int(b[s + 2]), data=b[s + h:s + t - 1].tobytes(), bid=int(b[s + 1]))
                for s, t, h in zip(a_start[~a_d2].tolist(), tc[acc][~a_d2].tolist(), hc[acc][~a_d2].tolist())]
        self.counters.messages += len(msgs)
        batch = self._decode(acc[a_d2], groups, layout_id, layouts)
        batch.offsets = pc[acc[a_d2]] + self._abs
        batch.messages = msgs
        self._abs += consumed
        return self._unwrap(batch)

    def flush(self) -> MTData2Batch:
        """End of stream: classify the retained tail (truncated or bad) and return what remains."""
        return self.feed(b"", final=True)

    @staticmethod
    def _count_free(pc: np.ndarray, tc: np.ndarray, mask: np.ndarray, acc: np.ndarray) -> int:
        if not mask.any() or not acc.size:
            return int(mask.sum())
        s, e = pc[acc], pc[acc] + tc[acc]
        m = np.flatnonzero(mask)
        k = np.searchsorted(s, pc[m], side="right") - 1
        inside = (k >= 0) & (pc[m] < e[np.maximum(k, 0)])
        return int((~inside).sum())

    # ------------------------------------------------------------ checksums and layouts
    def _check_groups(self, b, pc, tc, hc, mids, layout_id, layouts):
        """Checksums and MTData2 layouts, one vector pass per distinct frame length.

        Returns (valid, is_mtdata2, groups) where groups is a list of (candidate indices, rows)
        with rows the (k, L) frame bytes (a view when the frames are back to back).
        """
        valid = np.zeros(pc.size, dtype=bool)
        groups: list[tuple[np.ndarray, np.ndarray]] = []
        if not pc.size:
            return valid, valid.copy(), groups
        order = np.argsort(tc, kind="stable")
        lengths, first = np.unique(tc[order], return_index=True)
        bounds = np.append(first, order.size)
        for j, length in enumerate(lengths.tolist()):
            gi = order[bounds[j]:bounds[j + 1]]
            rows = _rows(b, pc[gi], length)
            ok = rows[:, 1:].sum(axis=1, dtype=np.uint8) == 0
            valid[gi] = ok
            groups.append((gi, rows))
            d2 = np.flatnonzero(ok & (rows[:, 2] == MID.MTDATA2))
            hdr = int(hc[gi[0]])
            while d2.size:
                lay = parse_layout(rows[d2[0]], hdr)
                if lay is None:
                    d2 = d2[1:]
                    continue
                cols = np.array([o - 3 + k for _, o, _ in lay for k in range(3)], dtype=np.int64)
                expect = np.array([v for x, _, sz in lay for v in (x >> 8, x & 0xFF, sz)], dtype=np.uint8)
                match = (rows[d2][:, cols] == expect).all(axis=1) if cols.size else np.ones(d2.size, bool)
                layout_id[gi[d2[match]]] = len(layouts)
                layouts.append(lay)
                d2 = d2[~match]
        return valid, valid & (mids == MID.MTDATA2), groups

    def _decode(self, accepted: np.ndarray, groups, layout_id, layouts) -> MTData2Batch:
        """Decode the accepted MTData2 candidates (sorted by position) into one batch."""
        n = accepted.size
        f = _empty_fields(n)
        pos = np.full(layout_id.size, -1, dtype=np.int64)
        pos[accepted] = np.arange(n)
        for gi, rows in groups:
            out = pos[gi]
            sel = np.flatnonzero(out >= 0)
            if not sel.size:
                continue
            lids = layout_id[gi[sel]]
            for lid in np.unique(lids).tolist():
                s2 = sel[lids == lid]
                m = rows if s2.size == rows.shape[0] else rows[s2]
                dst = out[s2]
                for xdi, off, size in layouts[lid]:
                    base, prec, _ = split_xdi(xdi)
                    name = XDI_FIELD.get(base)
                    if name is None or item_size(xdi) is None:
                        cnt = self.counters.unknown_xdi.get(xdi, 0)
                        if cnt == 0:
                            log.warning("unknown MTData2 data ID 0x%04X (%d bytes) ignored", xdi, size)
                        self.counters.unknown_xdi[xdi] = cnt + s2.size
                        continue
                    raw = np.ascontiguousarray(m[:, off:off + size])
                    if base in XDI_INT_SIZE:
                        f[name][dst] = raw.view(">u2" if size == 2 else ">u4")[:, 0]
                    else:
                        k = XDI_COMPONENTS[base]
                        vals = _decode_real(raw, prec, k)
                        f[name][dst] = vals if k > 1 else vals[:, 0]
        return MTData2Batch(counter=f["packet_counter"], sample_time_fine=f["sample_time_fine"],
                            time_s=np.full(n, np.nan), acceleration=f["acceleration"],
                            rate_of_turn=f["rate_of_turn"], temperature=f["temperature"],
                            status_word=f["status_word"], delta_v=f["delta_v"], delta_q=f["delta_q"])

    # ------------------------------------------------------------------- counters/time
    def _unwrap(self, batch: MTData2Batch) -> MTData2Batch:
        c = self.counters
        raw = batch.counter
        have = raw >= 0
        c.frames_without_counter += int((~have).sum())
        keep = np.ones(raw.size, dtype=bool)
        ext = np.full(raw.size, -1, dtype=np.int64)
        hi = np.flatnonzero(have)
        if hi.size:
            r = raw[hi]
            prev = self._prev_raw if self._prev_counter is not None else int(r[0]) - 1
            d = np.diff(np.concatenate(([prev], r))) % 65536
            if np.all((d >= 1) & (d <= 32768)):
                base = self._prev_counter if self._prev_counter is not None else int(r[0]) - 1
                ext[hi] = base + np.cumsum(d)
                c.dropped_samples += int((d - 1).sum())
                self._prev_counter, self._prev_raw = int(ext[hi[-1]]), int(r[-1])
            else:
                self._unwrap_slow(hi, r, ext, keep)
        c.frames += int(keep.sum())
        out = {k: getattr(batch, k)[keep] for k in ("sample_time_fine", "acceleration", "rate_of_turn",
                                                   "temperature", "status_word", "delta_v", "delta_q")}
        stf = out["sample_time_fine"]
        stf_ext = np.full(stf.size, -1, dtype=np.int64)
        si = np.flatnonzero(stf >= 0)
        if si.size:
            t, cn = stf[si].astype(np.int64), ext[keep][si]
            first = self._prev_stf is None
            prev = int(t[0]) if first else self._prev_stf_raw
            prev_c = int(cn[0]) if first else self._prev_stf_counter
            d = np.diff(np.concatenate(([prev], t))) % self.wrap_ticks
            dc = np.diff(np.concatenate(([prev_c], cn)))
            known = (cn >= 0) & (np.concatenate(([prev_c], cn[:-1])) >= 0)
            if np.all(d <= np.where(known, dc * MAX_TICKS_PER_COUNT, self.wrap_ticks // 2)):
                base = int(t[0]) if first else self._prev_stf
                stf_ext[si] = base + np.cumsum(d)
                self._prev_stf, self._prev_stf_raw = int(stf_ext[si[-1]]), int(t[-1])
                self._prev_stf_counter, self._stf_cand = int(cn[-1]), None
            else:
                self._unwrap_time_slow(si, t.tolist(), cn.tolist(), stf_ext)
        time_s = np.where(stf_ext >= 0, stf_ext / SAMPLE_TIME_FINE_HZ, np.nan)
        return MTData2Batch(counter=ext[keep], sample_time_fine=stf_ext, time_s=time_s,
                            messages=batch.messages, offsets=batch.offsets[keep], **{k: v for k, v in out.items() if k != "sample_time_fine"})

    def _continues(self, t: int, cn: int, t0: int, c0: int) -> bool:
        """Whether SampleTimeFine ``t`` (counter ``cn``) continues ``t0`` (counter ``c0``): at
        most MAX_TICKS_PER_COUNT ticks per counter step ahead (counters -1: unknown, then within
        half the wrap ahead)."""
        d = (t - t0) % self.wrap_ticks
        return d <= ((cn - c0) * MAX_TICKS_PER_COUNT if cn >= 0 and c0 >= 0 else self.wrap_ticks // 2)

    def _unwrap_time_slow(self, si: np.ndarray, t: list[int], cn: list[int], stf_ext: np.ndarray) -> None:
        """Frame by frame: a stamp that does not continue the last accepted one gets no time
        (``time_outliers``) and is not the reference for the next; the second of two such stamps
        in a row that continue each other is a new time base (``time_restarts``), unwrapped from
        the last accepted stamp as a wrap."""
        c = self.counters
        for i, v, k in zip(si.tolist(), t, cn):
            if self._prev_stf is None or self._continues(v, k, self._prev_stf_raw, self._prev_stf_counter):
                restart = False
            elif self._stf_cand is not None and self._continues(v, k, *self._stf_cand):
                restart = True
            else:
                c.time_outliers += 1
                self._stf_cand = (v, k)
                continue
            if restart:
                log.warning("SampleTimeFine restarted at %d; a new time base", v)
                c.time_restarts += 1
                c.time_outliers -= 1
                behind = (self._prev_stf_raw - self._stf_cand[0]) % self.wrap_ticks
                if 0 < behind <= self.wrap_ticks // 2:      # began again: the device restarted
                    c.device_restarts += 1
            self._prev_stf = v if self._prev_stf is None else \
                self._prev_stf + (v - self._prev_stf_raw) % self.wrap_ticks
            self._prev_stf_raw, self._prev_stf_counter, self._stf_cand = v, k, None
            stf_ext[i] = self._prev_stf
        if c.time_outliers:
            log.warning("%d SampleTimeFine stamps rejected so far: not continuing the stamps before", c.time_outliers)

    def _unwrap_slow(self, hi: np.ndarray, r: np.ndarray, ext: np.ndarray, keep: np.ndarray) -> None:
        c = self.counters
        for i, v in zip(hi.tolist(), r.tolist()):
            if self._prev_counter is None:
                self._prev_counter, self._prev_raw = v, v
                ext[i] = v
                continue
            d = (v - self._prev_raw) % 65536
            if 1 <= d <= 32768:
                c.dropped_samples += d - 1
                self._prev_counter += d
                self._prev_raw = v
                ext[i] = self._prev_counter
                self._run = 0
                continue
            keep[i] = False
            c.out_of_order += 1
            self._run = self._run + 1 if v == (self._run_last + 1) % 65536 else 1
            self._run_last = v
            if self._run >= RESYNC_RUN:
                log.warning("PacketCounter restarted at %d; resynchronising", v)
                c.counter_restarts += 1
                c.out_of_order -= 1
                keep[i] = True
                self._prev_counter += 1
                self._prev_raw = v
                ext[i] = self._prev_counter
                self._run = 0
        if not keep.all():
            log.warning("%d MTData2 frames rejected: PacketCounter did not advance", int((~keep).sum()))


def decode_buffer(data: bytes | np.ndarray, wrap_ticks: int = SAMPLE_TIME_FINE_WRAP
                  ) -> tuple[MTData2Batch, DecodeCounters]:
    """Decode a complete byte buffer in one call (end of stream included)."""
    st = MTData2Stream(wrap_ticks=wrap_ticks)
    batch = st.feed(data, final=True)
    return batch, st.counters


__all__ = ["DecodeCounters", "MTData2Batch", "MTData2Stream", "decode_buffer", "parse_layout",
           "PRECISION_BYTES"]
