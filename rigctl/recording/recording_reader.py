"""The one place that opens a recording for reading and checks it (every command uses it).

:func:`open_recording` answers every way a file can fail to be a usable recording with one
:class:`rigctl.errors.InputError` naming the file and saying what to do, before any analysis
touches the data:

* the path: missing, a directory (a run directory: give its ``recording.h5``), empty, not HDF5;
* cut off: a file shorter than the end-of-file address its HDF5 superblock records (a copy that
  stopped, a full disk) is refused, whether or not the SWMR flags are set (a SWMR reader skips
  HDF5's own check, and would then read garbage or hang);
* a run in progress or cut off by a crash (HDF5's write flags still set) is opened as a SWMR
  reader (docs/data-format.md, "Reading a run in progress");
* the root attribute ``format`` must be :data:`rigctl.recording.recorder.FORMAT_NAME`;
* the datasets a command needs (``need``): present, each row of the shape and the kind of dtype
  :data:`rigctl.recording.recorder.LAYOUT` gives (a string-typed /imu/time is refused), the datasets of
  one group of the same length, /imu not empty;
* /imu's ``sample_rate_hz``: finite, > 0 and at most :data:`MAX_RATE_HZ`;
* /segments rows: ``0 <= first_sample <= last_sample <= `` the number of IMU samples.

Finiteness is checked where the data are read (:func:`check_finite`), block by block, so a
night's recording is not read twice.
"""
from __future__ import annotations

import ctypes
import errno
import mmap
import os
import sys
from collections.abc import Iterable
from pathlib import Path

import h5py
import numpy as np

from .checkpoint import HDF5_SIGNATURE, superblock_eof
from ..errors import InputError
from .foreign import import_hint
from .recorder import FORMAT_NAME, LAYOUT

#: highest sample rate a recording may declare, Hz
MAX_RATE_HZ = 1e6
#: largest magnitude a recorded value may have (SI): beyond it the data are not an IMU's
#: output (a unit or an import error: mg read as m/s^2 is 1e4, not 1e300)
PLAUSIBLE = {"imu/specific_force": 1e6, "imu/angular_rate": 1e5, "imu/time": 1e10}
#: what every message about the layout points to
LAYOUT_DOC = "see docs/data-format.md"

_KINDS = {np.dtype(np.float64).kind: "f", np.dtype(np.int32).kind: "iu", np.dtype(np.uint64).kind: "iu",
          "S": "S"}


def check_path(p: Path) -> None:
    """InputError naming ``p`` when it cannot be a recording before HDF5 opens it: a foreign log
    given where a recording goes (:func:`import_hint`), a directory, missing, unreadable, empty,
    not HDF5, or cut off (shorter than its superblock records; a SWMR reader would skip HDF5's
    own check and read garbage or hang)."""
    bag = import_hint(p)
    if bag is not None:
        raise InputError(bag, p)
    if p.is_dir():
        inside = p / "recording.h5"
        hint = f"give the recording inside it: {inside}" if inside.is_file() else \
            "give a recording .h5 file (a run directory holds recording.h5)"
        raise InputError("is a directory, not a recording", p, hint=hint)
    if not p.exists():
        raise InputError("no such file", p, hint="give the path of a rigctl recording (.h5)")
    try:
        size = p.stat().st_size
        with open(p, "rb") as fh:
            head = fh.read(8)
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", p) from None
    if size == 0:
        raise InputError("empty file (0 bytes)", p, hint="give a rigctl recording (.h5)")
    if head != HDF5_SIGNATURE:
        raise InputError("not an HDF5 file", p, hint="give a rigctl recording (.h5), or convert a CSV "
                                                     "log with rigctl import")
    eof = superblock_eof(p)
    if eof is not None and size < eof:
        raise InputError(f"cut off: {size} bytes of the {eof} its HDF5 header records "
                         f"({100.0 * size / eof:.0f} %)", p,
                         hint="an incomplete copy or a full disk; copy it again from the run directory")


def unwritable_reason(p: Path) -> str | None:
    """Why the file or directory ``p`` cannot be written ('read-only file system', 'no write
    permission'), or None when it can (or does not exist: its creation reports its own error)."""
    try:
        if os.statvfs(p).f_flag & os.ST_RDONLY:
            return "read-only file system"
    except OSError:
        return None
    return None if os.access(p, os.W_OK) else "no write permission"


def check_results_writable(p: Path, command: str, group: str) -> None:
    """InputError, before the analysis, when ``command`` could not store /results/``group`` in
    the recording ``p`` (a read-only share, another user's run): one line saying so and what to
    do, instead of an HDF5 'unable to open file' after minutes of work."""
    why = unwritable_reason(p) if p.is_file() else None
    if why:
        raise InputError(f"cannot store the results in it ({why})", p,
                         hint=f"{command} writes /results/{group} into the recording: copy it to a "
                              "writable directory and analyse the copy")


def _open_h5(p: Path) -> h5py.File:
    try:
        return h5py.File(p, "r")
    except OSError:
        pass
    try:  # a run in progress, or one cut off by a crash: its write flags are still set
        return h5py.File(p, "r", libver="latest", swmr=True)
    except (OSError, RuntimeError, ValueError) as exc:
        raise InputError(f"cannot be read as HDF5 ({exc})", p,
                         hint="the file is damaged; copy it again from the run directory") from None


def _check_dataset(f: h5py.File, p: Path, name: str) -> h5py.Dataset:
    group, _, dname = name.partition("/")
    try:
        obj = f.get(name)
    except (OSError, RuntimeError, KeyError, ValueError) as exc:
        raise InputError(f"/{name} cannot be read ({exc})", p, hint="the file is damaged") from None
    if obj is None:
        raise InputError(f"the recording has no /{name}", p, hint=LAYOUT_DOC)
    if not isinstance(obj, h5py.Dataset):
        raise InputError(f"/{name} is not a dataset", p, hint=LAYOUT_DOC)
    spec = LAYOUT.get(group, {}).get(dname)
    if spec is not None:
        shape, dtype, units = spec
        if obj.ndim != 1 + len(shape) or tuple(obj.shape[1:]) != tuple(shape):
            want = "(N" + "".join(f", {k}" for k in shape) + ")"
            raise InputError(f"/{name} has shape {obj.shape}, expected {want}", p, hint=LAYOUT_DOC)
        want_kinds = _KINDS.get(np.dtype(dtype).kind, np.dtype(dtype).kind)
        if obj.dtype.kind not in want_kinds:
            raise InputError(f"/{name} has dtype {obj.dtype}, expected {np.dtype(dtype)}"
                             + (f" ({units})" if units else ""), p, hint=LAYOUT_DOC)
    return obj


def _sample_rate(f: h5py.File, p: Path) -> float:
    rate = f["imu"].attrs.get("sample_rate_hz") if "imu" in f else None
    try:
        value = float(rate) if rate is not None else float("nan")
    except (TypeError, ValueError):
        value = float("nan")
    if not (np.isfinite(value) and 0.0 < value <= MAX_RATE_HZ):
        raise InputError(f"/imu sample_rate_hz is {rate!r}: a sample rate must be a finite number of Hz "
                         f"in (0, {MAX_RATE_HZ:g}]", p, hint="record with rigctl, or import with --rate HZ")
    return value


def _check_segments(f: h5py.File, p: Path, n_imu: int) -> None:
    seg = f["segments"]
    if "first_sample" not in seg or "last_sample" not in seg:
        return  # a reader that needs them asked for them (need=...) and was refused already
    first = np.asarray(seg["first_sample"][()], dtype=np.int64)
    last = np.asarray(seg["last_sample"][()], dtype=np.int64)
    labels = seg["label"][()] if "label" in seg else None
    bad = np.flatnonzero((first < 0) | (last < first) | (last > n_imu))
    if bad.size:
        i = int(bad[0])
        label = labels[i].decode("utf-8", "replace") if labels is not None else ""
        raise InputError(f"/segments row {i} ({label!r}) covers IMU samples [{first[i]}, {last[i]}), "
                         f"outside the {n_imu} samples recorded"
                         + (f" ({bad.size} such rows)" if bad.size > 1 else ""), p,
                         hint="the segment table does not match the data; re-import or re-record")


def check_layout(f: h5py.File, p: Path, need: Iterable[str], check_present: bool = True,
                 groups: Iterable[str] = ()) -> dict[str, dict[str, int]]:
    """Check the open file ``f`` (the recording ``p``): its root attribute ``format``, the
    datasets ``need`` (as :func:`open_recording` takes them) and with ``check_present`` every
    dataset of the layout the file has -- present, each row of the layout's shape and kind of
    dtype -- and the ``groups`` (e.g. "meta", read for its attributes) present. InputError naming
    ``p`` and the first thing wrong. Returns the rows of each dataset checked, by group
    ({"imu": {"imu/time": N, ...}}); their lengths are not compared here."""
    try:
        fmt = f.attrs.get("format")
    except (OSError, RuntimeError) as exc:
        raise InputError(f"cannot be read as HDF5 ({exc})", p, hint="the file is damaged") from None
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", "replace")
    if fmt != FORMAT_NAME:
        raise InputError(f"not a rigctl recording (root attribute format != {FORMAT_NAME!r})", p,
                         hint="see docs/data-format.md, or convert a CSV log with rigctl import")
    for g in groups:
        if not isinstance(f.get(g), h5py.Group):
            raise InputError(f"the recording has no group /{g}", p, hint=LAYOUT_DOC)
    names: list[str] = []
    for n in need:
        names += [f"{n}/{d}" for d in LAYOUT[n]] if n in LAYOUT else [n]
    if check_present:
        names += [f"{g}/{d}" for g, ds in LAYOUT.items() if g in f for d in ds if d in f[g]]
    lengths: dict[str, dict[str, int]] = {}
    for name in dict.fromkeys(names):
        ds = _check_dataset(f, p, name)
        lengths.setdefault(name.partition("/")[0], {})[name] = int(ds.shape[0])
    return lengths


def check_need(f: h5py.File, p: Path, need: Iterable[str], check_present: bool = True) -> dict[str, dict[str, int]]:
    """Check on the open file ``f`` (the recording ``p``) the datasets ``need`` as
    :func:`open_recording` does (:func:`check_layout`, and the datasets of each group checked of
    one length): also for a reader that learns only from the open file what more it reads (its
    /events when it has them). InputError naming ``p``; returns :func:`check_layout`'s lengths."""
    lengths = check_layout(f, p, need, check_present)
    for group, lens in lengths.items():
        if len(set(lens.values())) > 1:
            what = ", ".join(f"/{k}: {v}" for k, v in lens.items())
            raise InputError(f"the datasets of /{group} differ in length ({what})", p,
                             hint="a damaged or hand-edited file; re-record or re-import it")
    return lengths


def open_recording(path: str | Path, need: Iterable[str] = ("imu/time",),
                   check_present: bool = True) -> h5py.File:
    """Open the rigctl recording ``path`` read-only and check it (see the module docstring).

    Args:
        path: the recording (.h5).
        need: datasets the caller reads, as "group/name" (e.g. "imu/angular_rate",
            "segments/first_sample"); a group name alone ("segments") means every dataset of it
            in the layout that the file must have for the caller.
        check_present: also check every dataset of the layout the file has (default: a file
            whose layout is broken anywhere is refused by every command). With ``need`` empty
            (a reader of whatever is there, e.g. the report) /imu may be empty.

    Returns the open file (a context manager); raises InputError naming the file."""
    p = Path(path)
    check_path(p)
    f = _open_h5(p)
    try:
        lengths = check_need(f, p, need, check_present)
        if "imu" in lengths:
            n_imu = next(iter(lengths["imu"].values()))
            if n_imu == 0 and need:
                raise InputError("/imu is empty (no samples)", p, hint="the run recorded no IMU data")
            if n_imu:
                _sample_rate(f, p)
            if "segments" in lengths:
                _check_segments(f, p, n_imu)
        return f
    except BaseException:
        f.close()
        raise


def sample_rate(f: h5py.File) -> float:
    """/imu's sample_rate_hz of a file :func:`open_recording` checked, Hz."""
    return _sample_rate(f, Path(f.filename))


def check_finite(path: str | Path, name: str, block: np.ndarray, first_row: int = 0) -> None:
    """InputError naming ``path``, the dataset ``name`` and the first row when ``block`` (rows
    ``first_row``...) holds NaN, infinity, or a magnitude beyond :data:`PLAUSIBLE`."""
    a = np.asarray(block, dtype=np.float64)
    key = name.lstrip("/")
    limit = PLAUSIBLE.get(key, np.inf)
    if a.size:  # the common case in two read-only passes (NaN propagates into max and min)
        hi, lo = float(np.max(a)), float(np.min(a))
        if np.isfinite(hi) and np.isfinite(lo) and max(hi, -lo) <= limit:
            return
    ok = np.isfinite(a) & (np.abs(a) <= limit)
    if ok.all():
        return
    rows = ~ok.reshape(a.shape[0], -1).all(axis=1) if a.ndim > 1 else ~ok
    k = int(np.flatnonzero(rows)[0])
    what = "NaN or infinite values" if not np.isfinite(a[k]).all() else \
        f"values beyond +-{limit:g} (SI units: not an IMU's output)"
    scale = "acc=counts:SCALE m/s^2" if "force" in key else "gyr=counts:SCALE rad/s"
    every = bool(rows.all()) and bool(np.isfinite(a).all())  # all beyond the limit: a unit error
    raise InputError(f"/{key} holds {what} (first at row {first_row + k}, {int(rows.sum())} rows in rows "
                     f"{first_row}..{first_row + a.shape[0] - 1})", path,
                     hint=f"every row: a unit or scale error, not bad samples; re-import with the "
                          f"column's scale (rigctl import --units '{scale}')" if every else
                     "the sensor or the import produced invalid samples; cut them out "
                     "(rigctl import --segments) or re-record")


def _madvise_fn():  # -> the C library's madvise (ctypes: the call releases the GIL) or None
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None, use_errno=True).madvise
    except (OSError, AttributeError):  # pragma: no cover - a libc without it
        return None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    fn.restype = ctypes.c_int
    return fn


_MADVISE = _madvise_fn()
#: Linux's madvise advice: map the pages of a range now (5.14+: before it EINVAL, and the pages
#: are mapped at their first touch instead), and drop a range's pages from the mapping
MADV_POPULATE_READ, MADV_DONTNEED = 22, 4
_POPULATE = [True]  # cleared when the kernel does not know MADV_POPULATE_READ
#: :meth:`RowReader.view` gives the rows where they lie in the mapped file (False: it reads them
#: into the buffer, as :meth:`RowReader.read`)
MAP_ROWS = True
#: bytes around a page fault the kernel maps with it (Linux's fault_around_bytes, by default)
FAULT_AROUND = 1 << 16
#: a dataset is mapped only where its runs of adjacent chunks are this long (median, bytes):
#: the recorder's interleaved 8192-row chunks (196 kB runs of a 3-axis dataset) cost more
#: mapped than copied -- each run's edges map the other datasets' pages around them
#: (FAULT_AROUND) and drop them again -- so they are copied (docs/allan.md)
MAP_MIN_RUN_BYTES = 1 << 20


class RowPieces:
    """Rows [a, b) of a dataset where they lie in the file, not copied (:meth:`RowReader.view`):
    ``base`` is the whole file mapped read-only as the dataset's dtype, one lane per byte
    offset modulo the dtype's size (base[r, k]: the value at byte r + k * size; HDF5 does not
    align its chunks), and the rows are the pieces ``base[lanes[p], starts[p]: starts[p] +
    rows[p] * width]`` (``width`` values per row), one after the other -- the dataset's chunks
    that lie next to each other in the file make one piece. ``shape``, ``ndim`` and ``dtype``
    are the rows' as an array's. :meth:`dense` copies them into the reader's buffer (for code
    that needs one array); :meth:`release` drops their pages from the process' mapping once
    nothing reads them (they stay in the page cache), so that the resident memory holds only
    the pieces in use."""

    def __init__(self, base: np.ndarray, lanes: np.ndarray, starts: np.ndarray,
                 rows: np.ndarray, row_shape: tuple[int, ...], out: np.ndarray,
                 spans: list[tuple[int, int]]):
        self.base, self.lanes, self.starts, self.rows = base, lanes, starts, rows
        self.shape = (int(np.sum(rows)), *row_shape)
        self.ndim = len(self.shape)
        self.dtype = base.dtype
        self._out = out
        self._spans = spans  # (address, bytes) of the pieces' pages
        self._dense: np.ndarray | None = None

    def dense(self) -> np.ndarray:
        """The rows as one array (copied into the reader's buffer once)."""
        if self._dense is None:
            dst = self._out[: self.shape[0]]
            w = int(np.prod(self.shape[1:], dtype=np.int64))
            pos = 0
            for ln, s, m in zip(self.lanes.tolist(), self.starts.tolist(), self.rows.tolist()):
                dst[pos: pos + m] = self.base[ln, s: s + m * w].reshape(m, *self.shape[1:])
                pos += m
            self._dense = dst
        return self._dense

    def release(self) -> None:
        """Drop the pieces' pages from this process' mapping (MADV_DONTNEED: a later read
        maps them again from the page cache)."""
        spans, self._spans = self._spans, []
        for addr, nbytes in spans:
            _MADVISE(addr, nbytes, MADV_DONTNEED)


def as_array(rows: np.ndarray | RowPieces) -> np.ndarray:
    """Rows from :meth:`RowReader.view` as one array (a :class:`RowPieces` copied)."""
    return rows.dense() if isinstance(rows, RowPieces) else rows


def release(rows: np.ndarray | RowPieces) -> None:
    """Rows from :meth:`RowReader.view` read for the last time (:meth:`RowPieces.release`)."""
    if isinstance(rows, RowPieces):
        rows.release()


class RowReader:
    """Reads rows [a, b) of a dataset into a given buffer, the same values as h5py's
    ``read_direct``. When the dataset is stored as HDF5 writes it by default -- contiguous, or
    chunked with whole rows per chunk, no filters (no compression), the buffer's dtype in
    native byte order -- its bytes are the rows themselves, so the rows are read with
    ``os.preadv`` straight from the chunks' file offsets (HDF5's chunk index, read once;
    adjacent chunks in one call). That copies the page cache into the buffer and nothing
    else, and it releases the GIL: another thread's Python work goes on while it reads (h5py
    holds the GIL for the whole read). Any other layout (compressed, partial-width chunks,
    a chunk not yet written, a file opened as a SWMR reader) goes through h5py.

    :meth:`view` gives the same rows without the copy, where they lie in the file mapped
    read-only (Linux; each chunk's offset a multiple of the dtype's size): their pages mapped
    at once (MADV_POPULATE_READ, without the GIL) cost about half the CPU of copying them."""

    def __init__(self, f: h5py.File, name: str):
        self.ds = f[name]
        self.direct: list[tuple[int, int, int]] | None = None  # (first row, rows, file offset)
        self._fd = -1
        self._base: np.ndarray | None = None  # the whole file mapped, as the dtype (view)
        self._mapped = False
        try:
            self._plan(f)
        except (AttributeError, OSError, RuntimeError, ValueError, TypeError):
            self.direct = None
        if self.direct is not None:
            try:
                self._fd = os.open(f.filename, os.O_RDONLY)
            except OSError:
                self.direct = None

    def _plan(self, f: h5py.File) -> None:
        ds = self.ds
        if getattr(f, "swmr_mode", False) or ds.dtype.byteorder not in ("=", "<" if
                                                                         np.little_endian else ">"):
            return
        if ds.dtype.kind not in "fiu" or ds.ndim < 1 or ds.size == 0:
            return
        row_bytes = ds.dtype.itemsize * int(np.prod(ds.shape[1:], dtype=np.int64))
        dcpl = ds.id.get_create_plist()
        layout = dcpl.get_layout()
        if dcpl.get_nfilters():
            return
        if layout == h5py.h5d.CONTIGUOUS:
            off = ds.id.get_offset()
            if off is None:
                return
            self.direct = [(0, ds.shape[0], int(off))]
        elif layout == h5py.h5d.CHUNKED:
            if tuple(ds.chunks[1:]) != tuple(ds.shape[1:]):
                return
            rows = int(ds.chunks[0])
            got: list[tuple[int, int, int]] = []
            ds.id.chunk_iter(lambda ci: got.append((int(ci.chunk_offset[0]), int(ci.byte_offset),
                                                    int(ci.filter_mask))))
            got.sort()
            if any(m for _, _, m in got):
                return
            # a full index of whole chunks: chunk k holds rows k*rows .. (k+1)*rows - 1
            if [r for r, _, _ in got] != list(range(0, ds.shape[0], rows)):
                return
            self.direct = [(r, min(rows, ds.shape[0] - r), off) for r, off, _ in got]
        self.row_bytes = row_bytes
        self._starts = np.array([r for r, _, _ in self.direct or []], dtype=np.int64)
        # the runs of chunks that lie one after the other in the file: (first row, rows, offset)
        runs: list[list[int]] = []
        for r, n, off in self.direct or []:
            if runs and runs[-1][2] + runs[-1][1] * row_bytes == off:
                runs[-1][1] += n
            else:
                runs.append([r, n, off])
        self._runs = np.array(runs, dtype=np.int64).reshape(-1, 3)

    def read(self, a: int, b: int, out: np.ndarray) -> np.ndarray:
        """Rows [a, b) into out[:b - a] (C-contiguous, the dataset's dtype and row shape);
        returns that view."""
        return self._copy(a, b, out)

    def _copy(self, a: int, b: int, out: np.ndarray) -> np.ndarray:
        dst = out[: b - a]
        if b <= a:
            return dst
        if self.direct is None or dst.dtype != self.ds.dtype or not dst.flags.c_contiguous:
            self.ds.read_direct(dst, np.s_[a:b], np.s_[0:b - a])
            return dst
        mv = memoryview(dst.reshape(-1).view(np.uint8))
        rb = self.row_bytes
        k = int(np.searchsorted(self._starts, a, side="right")) - 1
        pos = 0
        while a < b:
            r0, n, off = self.direct[k]
            lo = a - r0
            # extend over the following chunks that lie right after this one in the file
            end_off = off + n * rb
            j = k
            while j + 1 < len(self.direct) and self.direct[j][0] + self.direct[j][1] < b \
                    and self.direct[j + 1][2] == end_off:
                j += 1
                end_off += self.direct[j][1] * rb
            hi = min(b, self.direct[j][0] + self.direct[j][1])
            nbytes = (hi - a) * rb
            start = off + lo * rb
            got = 0
            while got < nbytes:
                r = os.preadv(self._fd, [mv[pos + got: pos + nbytes]], start + got)
                if r <= 0:
                    raise OSError(f"{self.ds.file.filename}: short read at byte {start + got}")
                got += r
            pos += nbytes
            a = hi
            k = j + 1
        return dst

    def _map(self) -> np.ndarray | None:
        """The whole file mapped read-only as the dataset's dtype (once; :class:`RowPieces`'
        lanes), or None where the rows are not viewed there (not Linux, h5py's layouts, runs
        of adjacent chunks shorter than :data:`MAP_MIN_RUN_BYTES`, a chunk that would reach
        beyond the lanes: in the file's last bytes, or beyond its end)."""
        if self._mapped:
            return self._base
        self._mapped = True
        if not MAP_ROWS or _MADVISE is None or self.direct is None or not len(self._runs) \
                or np.median(self._runs[:, 1]) * self.row_bytes < MAP_MIN_RUN_BYTES:
            return None
        item = self.ds.dtype.itemsize
        try:
            size = os.fstat(self._fd).st_size
            count = (size - item + 1) // item  # values per lane (each lane within the file)
            ends = self._runs[:, 2] + self._runs[:, 1] * self.row_bytes
            if count < 1 or int(np.max(ends - self._runs[:, 2] % item)) > count * item:
                return None
            mm = mmap.mmap(self._fd, size, access=mmap.ACCESS_READ)
        except (OSError, ValueError):
            return None
        self._mm = mm
        self._addr = np.frombuffer(mm, dtype=np.uint8).ctypes.data
        self._size = size
        self._base = np.ndarray((item, count), dtype=self.ds.dtype, buffer=mm,
                                strides=(1, item))
        return self._base

    def view(self, a: int, b: int, out: np.ndarray) -> RowPieces | np.ndarray:
        """Rows [a, b): as :class:`RowPieces` of the mapped file where the layout allows
        (:meth:`_map`), their pages mapped now (the read: without the GIL); else read into
        ``out`` as :meth:`read` does. The caller calls :meth:`RowPieces.release` once nothing
        reads the pieces any more, and :func:`as_array` where it needs one array."""
        base = self._map() if b > a else None
        if base is None:
            return self._copy(a, b, out)
        runs = self._runs
        k0 = int(np.searchsorted(runs[:, 0], a, side="right")) - 1
        k1 = int(np.searchsorted(runs[:, 0], b - 1, side="right"))
        r0, n, off = runs[k0:k1, 0], runs[k0:k1, 1], runs[k0:k1, 2]
        lo, hi = np.maximum(r0, a), np.minimum(r0 + n, b)
        first = off + (lo - r0) * self.row_bytes  # byte offsets of the pieces
        nbytes = (hi - lo) * self.row_bytes
        if _POPULATE[0]:
            for addr, m in self._spans(first, first + nbytes, mmap.PAGESIZE):
                if _MADVISE(addr, m, MADV_POPULATE_READ) and ctypes.get_errno() == errno.EINVAL:
                    _POPULATE[0] = False  # (before Linux 5.14) the pages map at their first touch
                    break
        item = self.ds.dtype.itemsize
        # a page fault maps the pages around it too (up to FAULT_AROUND bytes, of other
        # datasets' chunks where the recorder interleaves them): released with the pieces
        return RowPieces(base, first % item, first // item, hi - lo, tuple(self.ds.shape[1:]), out,
                         self._spans(first, first + nbytes, max(FAULT_AROUND, mmap.PAGESIZE)))

    def _spans(self, first: np.ndarray, end: np.ndarray, align: int) -> list[tuple[int, int]]:
        """(address, bytes) of the mapped file's bytes [first, end) of each piece, widened to
        multiples of ``align``, the overlapping ones merged."""
        out: list[tuple[int, int]] = []
        for s, e in zip((first - first % align).tolist(), (-(-end // align) * align).tolist()):
            e = min(e, self._size)
            if out and out[-1][0] <= s <= out[-1][1]:  # (file order)
                out[-1] = (out[-1][0], max(out[-1][1], e))
            else:
                out.append((s, e))
        return [(self._addr + s, e - s) for s, e in out]

    def close(self) -> None:
        """Close the file. The mapping is not closed here: numpy's arrays over it (``_base``,
        the lanes every :class:`RowPieces` reads) hold the mmap object but no buffer export, so
        ``mmap.close()`` would unmap it under pieces still read -- a task of an abandoned
        analysis still copying a chunk segfaulted the process. Dropping this reader's
        references leaves the mapping to the last array over it: it is unmapped when that one
        goes."""
        self._base = None
        self._mm = None
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __del__(self) -> None:  # pragma: no cover - closed explicitly by the callers
        self.close()


__all__ = ["open_recording", "check_finite", "sample_rate", "MAX_RATE_HZ", "RowReader", "RowPieces",
           "as_array", "release"]
