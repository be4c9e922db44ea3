"""Checkpoints on disk, and making a recording cut off by a crash writable again.

After every complete step the runner writes ``<run dir>/checkpoint.json`` atomically (write a
temporary file, fsync, ``os.replace``, fsync the directory): a crash or power loss at any moment
leaves either the previous or the new checkpoint, never a torn one. ``rigctl resume RUN`` reads it
to continue the run from the step after the last complete one, into the same recording.

HDF5 (1.10 and later) marks a file open for writing in its superblock's status flags; after
``kill -9`` the flags stay set and the library refuses to open the file for writing (and
non-SWMR readers refuse to read it) with "file is already open for write (may use <h5clear file>
...)". :func:`clear_status_flags` does what ``h5clear -s --increment`` does, without the tool: it
zeroes the flags of the version 2/3 superblock, raises the stored end-of-file address to at least
the real file size (so new allocations never overwrite data a crash left beyond it) and rewrites
the superblock checksum (Jenkins' lookup3, as HDF5 uses).
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..clock import utc_now
from ..errors import InputError
from .shield import shielded

CHECKPOINT_NAME = "checkpoint.json"
CHECKPOINT_SCHEMA = 1
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


@dataclass
class Checkpoint:
    """State of a run after its last complete step (file times in s on the recording's base)."""

    procedure_path: str
    overrides: dict[str, Any]
    source_sha256: dict[str, str]
    config_file: str = "config.yaml"
    recording: str = "recording.h5"
    last_step: int = -1          # Step.index of the last complete step, -1 = none yet
    n_imu: int = 0               # IMU rows in the recording after that step
    n_segments: int = 0
    t_file: float = 0.0          # file time at the checkpoint, s
    sessions: int = 1            # 1 + number of resumes
    status: str = "running"      # running | complete | interrupted | failed
    #: the solvers of the procedure's solve steps, in order (run once the recording is complete)
    solvers: list[str] = field(default_factory=list)
    #: their state once the recording is complete: running | done | interrupted | failed;
    #: "" before (or in a checkpoint written before rigctl kept it). ``rigctl resume`` of a
    #: complete run whose analysis is not done runs the analysis only
    analysis: str = ""
    updated_utc: str = ""
    schema: int = CHECKPOINT_SCHEMA
    extra: dict[str, Any] = field(default_factory=dict)


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def try_lock(path: Path) -> tuple[int | None, str]:
    """Take an exclusive lock on ``path`` (created 0600) without waiting: ``(fd, "")`` when taken
    -- the file then holds this process's pid; close ``fd`` to release it (the kernel releases it
    when the process dies, kill -9 too) -- or ``(None, pid)`` with the holder's pid ('' if
    unknown) when another process, or another open of this one, holds it."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 64).decode(errors="replace").strip()
        os.close(fd)
        return None, holder
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd, ""


def write_atomic(path: Path, data: bytes) -> None:
    """Replace ``path`` by ``data`` atomically and durably (temp + fsync + os.replace), whole
    even when an interruption arrives meanwhile (:func:`rigctl.recording.shield.shielded`)."""
    tmp = path.with_name(f".{path.name}.tmp")
    with shielded():
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            os.write(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def save(run_dir: Path, ckpt: Checkpoint) -> None:
    ckpt.updated_utc = utc_now()
    write_atomic(run_dir / CHECKPOINT_NAME, json.dumps(asdict(ckpt), indent=1).encode())


class CheckpointError(InputError):
    """No usable checkpoint in a run directory (invalid input: exit code 2, rigctl.errors)."""


def load(run_dir: Path) -> Checkpoint:
    path = run_dir / CHECKPOINT_NAME
    try:
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CheckpointError(f"{run_dir}: no {CHECKPOINT_NAME} (the run did not get far enough "
                              "to be resumed, or it is not a rigctl run directory)") from None
    except (OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: unreadable checkpoint: {exc}") from None
    if not isinstance(raw, dict) or raw.get("schema") != CHECKPOINT_SCHEMA:
        raise CheckpointError(f"{path}: not a rigctl checkpoint of schema {CHECKPOINT_SCHEMA}")
    known = set(Checkpoint.__dataclass_fields__)
    try:
        return Checkpoint(**{k: v for k, v in raw.items() if k in known})
    except TypeError as exc:
        raise CheckpointError(f"{path}: incomplete checkpoint: {exc}") from None


# -- HDF5 superblock status flags ----------------------------------------------------------------
_M32 = 0xFFFFFFFF


def _rot(x: int, k: int) -> int:
    return ((x << k) | (x >> (32 - k))) & _M32


def lookup3(data: bytes, initval: int = 0) -> int:
    """Bob Jenkins' lookup3 ``hashlittle`` of ``data`` (the checksum of HDF5 metadata)."""
    n = len(data)
    a = b = c = (0xDEADBEEF + n + initval) & _M32
    i = 0
    while n - i > 12:
        a = (a + int.from_bytes(data[i:i + 4], "little")) & _M32
        b = (b + int.from_bytes(data[i + 4:i + 8], "little")) & _M32
        c = (c + int.from_bytes(data[i + 8:i + 12], "little")) & _M32
        a = (a - c) & _M32; a ^= _rot(c, 4); c = (c + b) & _M32    # noqa: E702 - the mix step
        b = (b - a) & _M32; b ^= _rot(a, 6); a = (a + c) & _M32    # noqa: E702
        c = (c - b) & _M32; c ^= _rot(b, 8); b = (b + a) & _M32    # noqa: E702
        a = (a - c) & _M32; a ^= _rot(c, 16); c = (c + b) & _M32   # noqa: E702
        b = (b - a) & _M32; b ^= _rot(a, 19); a = (a + c) & _M32   # noqa: E702
        c = (c - b) & _M32; c ^= _rot(b, 4); b = (b + a) & _M32    # noqa: E702
        i += 12
    tail = data[i:]
    if not tail:
        return c
    tail = tail + bytes(12 - len(tail))
    a = (a + int.from_bytes(tail[0:4], "little")) & _M32
    b = (b + int.from_bytes(tail[4:8], "little")) & _M32
    c = (c + int.from_bytes(tail[8:12], "little")) & _M32
    c = ((c ^ b) - _rot(b, 14)) & _M32  # final mixing
    a = ((a ^ c) - _rot(c, 11)) & _M32
    b = ((b ^ a) - _rot(a, 25)) & _M32
    c = ((c ^ b) - _rot(b, 16)) & _M32
    a = ((a ^ c) - _rot(c, 4)) & _M32
    b = ((b ^ a) - _rot(a, 14)) & _M32
    c = ((c ^ b) - _rot(b, 24)) & _M32
    return c


def status_flags(path: Path) -> int:
    """The superblock's file-consistency flags (bit 0 write, bit 2 SWMR write); -1 if v0/v1."""
    with open(path, "rb") as fh:
        head = fh.read(12)
    if head[:8] != HDF5_SIGNATURE:
        raise ValueError(f"{path}: not an HDF5 file (no superblock at offset 0)")
    return head[11] if head[8] in (2, 3) else -1


def superblock_eof(path: Path) -> int | None:
    """The end-of-file address (bytes, base address included) a version 2/3 superblock at
    offset 0 records; None for other superblocks (older files: HDF5 itself checks their size)
    or an unreadable one. A file shorter than this was cut off."""
    with open(path, "rb") as fh:
        sb = fh.read(48 + 16)
    if sb[:8] != HDF5_SIGNATURE or len(sb) < 12 or sb[8] not in (2, 3):
        return None
    so = sb[9]
    if so not in (2, 4, 8) or len(sb) < 12 + 4 * so + 4:
        return None
    end = 12 + 4 * so
    if int.from_bytes(sb[end:end + 4], "little") != lookup3(bytes(sb[:end])):
        return None
    base = int.from_bytes(sb[12:12 + so], "little")
    return base + int.from_bytes(sb[12 + 2 * so:12 + 3 * so], "little")


def clear_status_flags(path: Path) -> bool:
    """Clear the write/SWMR flags a crashed writer left; True if anything changed.

    Only for a file no process has open for writing (HDF5's own file locks are released by the
    kernel when a writer dies). Superblock v2/v3 at offset 0 (what ``libver="latest"`` writes):
    signature(8) version(1) sizeof_offsets(1) sizeof_lengths(1) flags(1) base(O) ext(O) eof(O)
    root(O) checksum(4).
    """
    with open(path, "r+b") as fh:
        sb = bytearray(fh.read(48 + 16))
        if sb[:8] != HDF5_SIGNATURE:
            raise ValueError(f"{path}: not an HDF5 file (no superblock at offset 0)")
        if sb[8] not in (2, 3):
            return False  # old superblocks have no status flags in this place
        so = sb[9]
        end = 12 + 4 * so
        if int.from_bytes(sb[end:end + 4], "little") != lookup3(bytes(sb[:end])):
            raise ValueError(f"{path}: superblock checksum mismatch, refusing to modify it")
        off_eof = 12 + 2 * so
        eof = int.from_bytes(sb[off_eof:off_eof + so], "little")
        size = os.fstat(fh.fileno()).st_size
        if sb[11] == 0 and eof >= size:
            return False
        sb[11] = 0
        sb[off_eof:off_eof + so] = max(eof, size).to_bytes(so, "little")
        sb[end:end + 4] = lookup3(bytes(sb[:end])).to_bytes(4, "little")
        fh.seek(0)
        fh.write(bytes(sb[:end + 4]))
        fh.flush()
        os.fsync(fh.fileno())
    return True
