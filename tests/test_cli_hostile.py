"""The whole CLI surface under hostile input (issue 16, item 4).

Every command and option is driven in-process through ``rigctl.cli.main(argv)`` (stdout and
stderr captured) with missing files, directories, empty files, non-HDF5 files, truncated and
cut-off (SWMR flags set) recordings, recordings missing each group and each dataset, NaN- and
inf-filled data, wrong dtypes (string time), an empty /imu, segment rows past the end, bad sample
rates, huge and negative numbers, unknown ``-p`` names, unreachable ports and a closed stdout.
A few cases also run as real subprocesses to prove the in-process harness sees what a user sees.

For every case: no traceback and no "internal error" on stderr, no Python warning raised, the
exit code is one the README documents and the one the case expects, an error message names the
file it is about (with its line where it has one) or the option, and no case hangs (each has a
wall-clock limit). The case count is printed in the terminal summary.
"""
from __future__ import annotations

import contextlib
import copy
import hashlib
import io
import json
import os
import pickle
import shutil
import signal
import subprocess
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from helpers import ROOT, rigctl_cmd

from rigctl import cli
from rigctl.recording.checkpoint import HDF5_SIGNATURE, lookup3
from rigctl.config.config import load_config
from rigctl.engine.procedure import load_procedure
from rigctl.recording.recorder import LAYOUT
from rigctl.run.runner import run_procedure
from rigctl.solvers import allan_fit

#: limit of one in-process case, s of progress time (run_case): the case's CPU time (all its
#: threads) plus the wall time during which none of its threads could run (blocked on I/O, a lock,
#: a lookup). Time its threads spent waiting for a CPU that other processes held does not count:
#: the file runs at background priority beside the real-time tests (tests/conftest.py). The
#: costliest cases take 6-7 s of CPU (reports drawing six axes of stored Allan results)
CASE_LIMIT_S = 30.0
#: exit codes the README documents
DOCUMENTED = {0, 1, 2, 130}


class CaseTimeout(Exception):
    pass


class BrokenStdout(io.TextIOBase):
    """A stdout whose reader has gone: every write raises BrokenPipeError."""

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self) -> None:
        raise BrokenPipeError(32, "Broken pipe")


@dataclass
class Case:
    argv: list[str]
    expect: set[int]            # acceptable exit codes
    names: list[str] = field(default_factory=list)  # an error message must name one of these
    closed_stdout: bool = False


@dataclass
class Outcome:
    code: int
    out: str
    err: str
    warnings: list[str]
    seconds: float


def _runnable_threads(skip: int) -> bool | None:
    """Whether a thread of this process other than ``skip`` (a native thread id) is running or
    waiting for a CPU (state R in Linux's /proc/self/task/*/stat), or None where /proc does not say."""
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return None
    for t in tids:
        if int(t) == skip:
            continue
        try:
            with open(f"/proc/self/task/{t}/stat") as fh:
                state = fh.read().rsplit(")", 1)[1].split()[0]
        except (OSError, IndexError):
            continue  # the thread has ended
        if state == "R":
            return True
    return False


def _cpu_s() -> float:
    """CPU time of this process (every thread), s."""
    t = os.times()
    return t.user + t.system


def run_case(argv: list[str], closed_stdout: bool = False) -> Outcome:
    """One case in this process; CaseTimeout once its progress time reaches CASE_LIMIT_S: its CPU
    time (every thread) plus the wall time during which none of its threads could run, sampled
    every 0.2 s. A hang blocked on I/O, a lock or a lookup counts in full, a busy loop by its CPU;
    the time its threads waited for a CPU that other processes held does not count (where /proc
    does not say, every wall second counts)."""
    out, err = (BrokenStdout() if closed_stdout else io.StringIO()), io.StringIO()
    why: list[str] = []

    def alarm(_signum, _frame):
        raise CaseTimeout(why[0] if why else f"no answer within {CASE_LIMIT_S:g} s")

    main, done = threading.get_ident(), threading.Event()
    cpu0 = _cpu_s()

    def watchdog() -> None:
        me = threading.get_native_id()
        blocked, last = 0.0, time.monotonic()
        while not done.wait(0.2):
            now = time.monotonic()
            if not _runnable_threads(me):  # (None: /proc says nothing; every second counts)
                blocked += now - last
            last = now
            cpu = _cpu_s() - cpu0
            if blocked + cpu > CASE_LIMIT_S:
                why.append(f"no answer within {CASE_LIMIT_S:g} s ({now - t0:.1f} s of wall time: "
                           f"{cpu:.1f} s of CPU, {blocked:.1f} s with no thread able to run)")
                signal.pthread_kill(main, signal.SIGALRM)
                return

    old = signal.signal(signal.SIGALRM, alarm)
    t0 = time.monotonic()
    dog = threading.Thread(target=watchdog, name="hostile-case-watchdog", daemon=True)
    dog.start()
    try:
        with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(out), \
                contextlib.redirect_stderr(err):
            warnings.simplefilter("always")
            code = cli.main(argv)
    finally:
        done.set()
        dog.join()
        signal.signal(signal.SIGALRM, old)
    return Outcome(code, "" if closed_stdout else out.getvalue(), err.getvalue(),
                   [f"{w.category.__name__}: {w.message} ({w.filename}:{w.lineno})" for w in caught],
                   time.monotonic() - t0)


class SharedWork:
    """A pure function's identical calls computed once across the cases: the first call with
    given arguments (compared byte for byte: their pickle) runs the function; a later call with
    the same arguments gets a deep copy of its result. A call that raises is not kept (each
    such call raises again), nor one whose arguments the call changed. Installed after the
    untimed warm-up, so that the first call with any arguments is made by a checked case: a
    warning it raises (the same for the same arguments) fails that case."""

    def __init__(self, fn):
        self.fn, self.done, self.lock = fn, {}, threading.Lock()
        self.calls = self.hits = 0

    def __call__(self, *args, **kwargs):
        try:
            key = hashlib.sha256(pickle.dumps((args, sorted(kwargs.items())), protocol=5)).digest()
        except (pickle.PicklingError, TypeError, AttributeError):
            return self.fn(*args, **kwargs)
        with self.lock:
            self.calls += 1
            kept = self.done.get(key)
            if kept is not None:
                self.hits += 1
        if kept is not None:
            return copy.deepcopy(kept)
        out = self.fn(*args, **kwargs)
        if hashlib.sha256(pickle.dumps((args, sorted(kwargs.items())), protocol=5)).digest() == key:
            with self.lock:
                self.done[key] = copy.deepcopy(out)
        return out


# -- recordings --------------------------------------------------------------------------------------
def _base_recording(tmp: Path) -> Path:
    """A short emulated 24-position run (virtual time), as `rigctl run` records it."""
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc = load_procedure(ROOT / "procedures" / "24pos.yaml", {"warmup": "5 s", "sample": "1 s"}, cfg.limits)
    res = run_procedure(proc, cfg, tmp / "runs", console=io.StringIO(), install_signals=False)
    assert res.exit_code == 0, res.message
    return res.recording


def _set_write_flags(path: Path) -> None:
    """Set the superblock's write + SWMR-write flags, as a writer killed mid-run leaves them."""
    with open(path, "r+b") as fh:
        sb = bytearray(fh.read(64))
        assert sb[:8] == HDF5_SIGNATURE and sb[8] in (2, 3)
        so = sb[9]
        end = 12 + 4 * so
        sb[11] = 0x05
        sb[end:end + 4] = lookup3(bytes(sb[:end])).to_bytes(4, "little")
        fh.seek(0)
        fh.write(bytes(sb[:end + 4]))


#: which recorded values each command reads ("sf" /imu/specific_force, "rate" angular_rate,
#: "time" /imu/time): NaN / inf there must be refused (2); elsewhere the command may run (0)
READS = {"allan": {"sf", "rate"}, "allan-gx": {"rate"}, "calibrate": {"time", "sf", "rate"},
         "apply-cal": {"sf", "rate"}, "sync": {"sf"}, "report": set(), "thermal": {"time", "sf", "rate"}}


def make_variants(base: Path, d: Path) -> tuple[dict[str, Path], dict[str, Path], dict[str, str]]:
    """(bad, partial, tags) recording variants: every reader must refuse a bad one whose tag is
    "file" or "layout" (exit 2, naming the file); a "data-sf|rate|time" one is refused by the
    commands that read those values (READS); a partial one lacks or spoils something a command
    may not need."""
    bad: dict[str, Path] = {}
    partial: dict[str, Path] = {}
    tags: dict[str, str] = {}
    raw = base.read_bytes()

    def copy(name: str) -> Path:
        p = d / f"{name}.h5"
        p.write_bytes(raw)
        return p

    bad["missing"] = d / "no-such-file.h5"
    empty_dir = d / "a-directory.h5"
    empty_dir.mkdir()
    bad["directory"] = empty_dir
    bad["run-directory"] = base.parent
    (d / "empty.h5").write_bytes(b"")
    bad["empty"] = d / "empty.h5"
    (d / "text.h5").write_text("time,ax,ay,az\n0,0,0,9.8\n")
    bad["text"] = d / "text.h5"
    (d / "random.h5").write_bytes(np.random.default_rng(1).bytes(4096))
    bad["random-bytes"] = d / "random.h5"
    (d / "sig-junk.h5").write_bytes(HDF5_SIGNATURE + b"\x00" * 100)
    bad["hdf5-signature-then-junk"] = d / "sig-junk.h5"
    for pct in (1, 10, 50, 90, 95, 99):
        p = d / f"truncated-{pct}.h5"
        p.write_bytes(raw[: len(raw) * pct // 100])
        bad[f"truncated-{pct}pct"] = p
        if pct in (50, 99):
            q = d / f"cut-off-swmr-truncated-{pct}.h5"
            q.write_bytes(raw[: len(raw) * pct // 100])
            _set_write_flags(q)
            bad[f"cut-off-swmr-truncated-{pct}pct"] = q
    with h5py.File(d / "other.h5", "w") as f:
        f.create_dataset("x", data=[1, 2, 3])
    bad["other-hdf5"] = d / "other.h5"

    def edit(name: str, fn, into: dict[str, Path]) -> None:
        p = copy(name)
        with h5py.File(p, "r+") as f:
            fn(f)
        into[name] = p

    edit("format-attribute-missing", lambda f: f.attrs.__delitem__("format"), bad)
    edit("format-attribute-other", lambda f: f.attrs.__setitem__("format", "imu-log"), bad)
    edit("group-missing-imu", lambda f: f.__delitem__("imu"), bad)
    edit("group-missing-segments", lambda f: f.__delitem__("segments"), partial)
    for g in ("table", "pulses", "events", "meta", "run", "truth", "results"):
        edit(f"group-missing-{g}", lambda f, g=g: f.__delitem__(g), partial)
    for g, ds in LAYOUT.items():
        for name in ds:
            short = {"time": "time", "specific_force": "sf", "angular_rate": "rate"}.get(name)
            target = bad if g == "imu" and short else partial
            edit(f"dataset-missing-{g}-{name}", lambda f, g=g, name=name: f[g].__delitem__(name), target)
            if target is bad:
                tags[f"dataset-missing-{g}-{name}"] = f"need-{short}"

    n = int(h5py.File(base, "r")["imu/time"].shape[0])

    def fill(group: str, name: str, value: float, rows=slice(None)):
        def fn(f):
            a = f[f"{group}/{name}"][()]
            a = a.astype(np.float64)
            a[rows] = value
            f[f"{group}/{name}"][...] = a
        return fn

    with h5py.File(base, "r") as f:  # a row inside a complete orientation segment
        k = [i for i, kind in enumerate(f["segments/kind"][()]) if kind == b"orientation"][4]
        row = int(f["segments/first_sample"][k] + f["segments/last_sample"][k]) // 2
    for name, fn, tag in (("nan-specific-force", fill("imu", "specific_force", np.nan), "data-sf"),
                          ("nan-angular-rate", fill("imu", "angular_rate", np.nan), "data-rate"),
                          ("inf-specific-force", fill("imu", "specific_force", np.inf), "data-sf"),
                          ("minus-inf-angular-rate", fill("imu", "angular_rate", -np.inf), "data-rate"),
                          ("nan-one-row-specific-force",
                           fill("imu", "specific_force", np.nan, slice(row, row + 1)), "data-sf"),
                          ("nan-imu-time", fill("imu", "time", np.nan), "data-time")):
        edit(name, fn, bad)
        tags[name] = tag
    edit("nan-table-angle", fill("table", "angle", np.nan), partial)
    edit("huge-specific-force", fill("imu", "specific_force", 1e300), bad)
    tags["huge-specific-force"] = "data-sf"
    edit("huge-negative-angular-rate", fill("imu", "angular_rate", -1e300), bad)
    tags["huge-negative-angular-rate"] = "data-rate"
    edit("nan-segment-times", fill("segments", "t_start", np.nan), partial)

    def retype(group: str, name: str, dtype: str):
        def fn(f):
            a = f[f"{group}/{name}"][()]
            del f[group][name]
            f[group].create_dataset(name, data=a.astype(dtype))
        return fn

    edit("string-imu-time", retype("imu", "time", "S24"), bad)
    edit("string-specific-force", retype("imu", "specific_force", "S24"), bad)
    edit("integer-imu-time", retype("imu", "time", "int64"), bad)

    def reshape(group: str, name: str, shape_fn):
        def fn(f):
            a = f[f"{group}/{name}"][()]
            del f[group][name]
            f[group].create_dataset(name, data=shape_fn(a))
        return fn

    edit("angular-rate-two-columns", reshape("imu", "angular_rate", lambda a: a[:, :2]), bad)
    edit("imu-time-shorter", reshape("imu", "time", lambda a: a[: len(a) // 2]), bad)

    def empty_imu(f):
        for name in list(f["imu"]):
            f["imu"][name].resize(0, axis=0)

    edit("empty-imu", empty_imu, bad)

    def seg(col: str, fn_val):
        def fn(f):
            a = f[f"segments/{col}"][()]
            f[f"segments/{col}"][...] = fn_val(a)
        return fn

    edit("segment-rows-past-end", seg("last_sample", lambda a: a + 10 * n), bad)
    edit("segment-first-negative", seg("first_sample", lambda a: a - 10 * n), bad)
    edit("segment-first-after-last", seg("first_sample", lambda a: a + 10 * n), bad)
    for label, value in (("zero", 0.0), ("negative", -100.0), ("nan", np.nan), ("inf", np.inf),
                         ("huge", 1e300), ("text", "fast")):
        edit(f"sample-rate-{label}", lambda f, v=value: f["imu"].attrs.__setitem__("sample_rate_hz", v), bad)
    edit("sample-rate-missing", lambda f: f["imu"].attrs.__delitem__("sample_rate_hz"), bad)
    for name in bad:
        tags.setdefault(name, "file")
    return bad, partial, tags


#: which datasets each command needs at all: a missing one must be refused (2)
NEEDS = {"allan": {"time", "sf", "rate"}, "allan-gx": {"time", "rate"}, "calibrate": {"time", "sf", "rate"},
         "apply-cal": {"time", "sf", "rate"}, "sync": {"sf"}, "report": {"time", "sf", "rate"},
         "thermal": {"time", "sf", "rate"}}


def expected(argv: list[str], tag: str) -> set[int]:
    """Exit codes a recording command (``argv``) may give on a bad variant tagged ``tag``."""
    kind = "allan-gx" if argv[0] == "allan" and "gx" in argv else argv[0]
    if "--noise" in argv and argv[-1] not in ("self", "allan"):  # the variant is the noise source: its
        return {0, 2} if tag.startswith("data-") else {2}        # /results/allan, if any, is read
    if tag.startswith("data-"):
        return {2} if tag[5:] in READS[kind] else {0, 2}
    if tag.startswith("need-"):
        return {2} if tag[5:] in NEEDS[kind] or kind == "sync" else {0, 2}
    return {2}


# -- procedures and configs ---------------------------------------------------------------------
def write_inputs(d: Path) -> dict[str, tuple[Path, int | None]]:
    """Hostile procedure / config files: name -> (path, line its error must name, or None)."""
    files: dict[str, tuple[Path, int | None]] = {}

    def put(name: str, text: str | bytes, line: int | None = None) -> None:
        p = d / name
        (p.write_bytes if isinstance(text, bytes) else p.write_text)(text)
        files[name] = (p, line)

    put("empty.yaml", "")
    put("binary.yaml", b"\x89PNG\r\n\x1a\n\x00\xff\xfe")
    put("bad-syntax.yaml", "steps:\n  - warmup: {duration: 5 s\n", 3)
    put("not-mapping.yaml", "- 1\n- 2\n", 1)
    put("no-steps.yaml", "procedure: x\n", 1)
    put("bad-duration.yaml", "steps:\n  - warmup:\n      duration: 15 parsecs\n", 3)
    put("negative-duration.yaml", "steps:\n  - warmup:\n      duration: -5 s\n", 3)
    put("huge-duration.yaml", "steps:\n  - warmup:\n      duration: 1e300 h\n", 3)
    put("nan-duration.yaml", "steps:\n  - warmup:\n      duration: .nan\n", 3)
    put("unknown-step.yaml", "steps:\n  - warmpu:\n      duration: 5 s\n", 2)
    put("unknown-include.yaml", "steps:\n  - include: nowhere.yaml\n", 2)
    put("self-include.yaml", "steps:\n  - include: self-include.yaml\n", 2)
    put("huge-angle.yaml", "steps:\n  - orientations:\n      list: [[1e300, 0, 0]]\n      sample: 1 s\n", None)
    put("cfg-empty.yaml", "")
    put("cfg-bad-clock.yaml", "clock: sideways\ntable: {driver: sim}\nimu: {driver: sim}\n", 1)
    put("cfg-negative-rate.yaml", "table: {driver: sim}\nimu: {driver: sim, rate_hz: -100}\n", 2)
    put("cfg-huge-rate.yaml", "table: {driver: sim}\nimu: {driver: sim, rate_hz: 1e300}\n", 2)
    put("cfg-unknown-key.yaml", "table: {driver: sim}\nimu: {driver: sim, rate_hx: 100}\n", 2)
    put("cfg-no-table.yaml", "imu: {driver: sim}\n", 1)
    wired = ("clock: real\ntable: {driver: acl, port: %s}\nimu: {driver: xsens, port: %s, rate_hz: 100}\n"
             "pulses: {driver: none}\n")
    put("cfg-missing-serial.yaml", wired % ("/dev/ttyUSB97", "/dev/ttyUSB98"))
    put("cfg-refused-tcp.yaml", wired % ("socket://127.0.0.1:9", "socket://127.0.0.1:9"))
    put("cfg-unknown-host.yaml", wired % ("socket://no-such-host.invalid:9", "/dev/ttyUSB98"))
    put("cfg-not-a-tty.yaml", wired % (str(d / "empty.yaml"), str(d / "empty.yaml")))
    return files


def _warm_up(good: Path, tmp: Path) -> None:
    """The analyses once, untimed, before any timed case: a fresh checkout has no numba kernel
    cache yet (the fast extra), and the first allan / calibrate would spend the kernels'
    compilation (~10 s of CPU; the report: matplotlib's import) inside one case's wall-clock
    limit -- with the other test worker on the cores (tests/conftest.py). calibrate runs on the
    good recording itself: its /results/calibration and calibration JSON are what the cases
    read (it was run twice, here on a copy and again on the good one). allan and report run on
    a copy, on one gyro and one accelerometer axis: the kernels, imports and code paths are the
    same for all six (which run on the good recording in the --taus decade / all cases). Two
    allan runs compile every kernel the three before did (fast mode at octave taus, which
    loads the same 25 numba cache entries as the default 95 taus and --whole; exact mode), in
    ~2.3 s of CPU instead of ~5.9 s once compiled."""
    warm = tmp / "warm-up.h5"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert cli.main(["calibrate", str(good), "--noise", "self"]) == 0  # /results/calibration
        shutil.copyfile(good, warm)
        for argv in (["allan", str(warm), "--axes", "gx,ax", "--taus", "octave"],
                     ["allan", str(warm), "--axes", "gx,ax", "--exact", "--taus", "8"],
                     ["report", str(warm), "--out", str(tmp / "warm-up-report")]):
            assert cli.main(argv) == 0, argv


def build_cases(tmp: Path) -> tuple[list[Case], dict[str, Path]]:
    d = tmp / "hostile"
    d.mkdir()
    base = _base_recording(tmp)
    good = d / "good.h5"
    shutil.copyfile(base, good)
    _warm_up(good, tmp)  # calibrates good.h5 (/results/calibration, good.calibration.json)
    cal_json = good.with_name("good.calibration.json")
    bad, partial, tags = make_variants(good, d)
    ins = write_inputs(d)
    out = d / "out"
    out.mkdir()
    cases: list[Case] = []

    def rec_cmds(p: Path) -> list[list[str]]:
        o = str(out / f"{p.stem}-corrected.h5")
        return [["allan", str(p)], ["allan", str(p), "--axes", "gx"], ["allan", str(p), "--whole", "--taus", "octave"],
                ["allan", str(p), "--exact", "--taus", "8"],
                ["calibrate", str(p)], ["calibrate", str(p), "--noise", "self", "--explain"],
                ["calibrate", str(p), "--noise", "allan"], ["calibrate", str(good), "--noise", str(p)],
                ["sync", str(p)], ["sync", str(p), "--timescale", "gps", "--axis", "x"],
                ["report", str(p), "--out", str(out / "report")],
                ["apply-cal", str(p), "-o", o, "--force"],
                ["apply-cal", str(p), "-o", o, "--force", "--calibration", str(cal_json)],
                ["thermal", str(p)], ["thermal", str(p), "--static", "--one-pose", "--window-s", "1"]]

    for name, p in bad.items():
        for argv in rec_cmds(p):
            cases.append(Case(argv, expected(argv, tags[name]), [str(p)]))
        if name.startswith(("missing", "directory", "run-directory", "empty", "text", "random", "hdf5-",
                            "truncated", "cut-off", "other-hdf5", "format-")):
            # the certificate reads only results: files no reader can use (a readable one runs
            # Chromium, not here)
            cases.append(Case(["certificate", str(p), "--out", str(out / "cert")], {2}, [str(p)]))
    # partial recordings: each command runs or refuses, naming the file; never a traceback
    # (allan on gx and ax: one gyro and one accelerometer channel go through the same reading,
    # layout check, segment / table / temperature use and fit as all six; the other four axes'
    # fits, ~0.5 s of CPU each, do not touch the part a variant lacks or spoils. All six axes run
    # on the good recording: the --taus decade / all cases)
    for name, p in partial.items():
        for argv in (["allan", str(p), "--axes", "gx,ax", "--taus", "octave"], ["calibrate", str(p), "--noise", "self"],
                     ["sync", str(p)], ["apply-cal", str(p), "-o", str(out / "x.h5"), "--force"],
                     ["thermal", str(p), "--one-pose"]):
            cases.append(Case(argv, {0, 1, 2}, [str(p)]))
    for name in ("group-missing-table", "group-missing-meta", "dataset-missing-imu-counter",
                 "nan-table-angle", "nan-segment-times"):
        cases.append(Case(["report", str(partial[name]), "--out", str(out / "r2")], {0, 1, 2}, [str(partial[name])]))

    # options: hostile values on a good recording
    g = str(good)
    for taus in ("0", "1", "-5", "1e9", "abc", "", "nan", "decade", "all"):
        cases.append(Case(["allan", g, "--taus", taus], {0} if taus in ("decade", "all") else {2}, ["--taus"]))
    # (GX and gyro_x are gx, any case: acb3cb3's one spelling per axis reads the old ones)
    for axes in ("", ",", "gx,qq", "gyro_q", "gx,gx", "GX"):
        cases.append(Case(["allan", g, "--axes", axes, "--taus", "octave"],
                          {0} if axes in ("gx,gx", "GX") else {2}, ["--axes"]))
    for opt in ("--natural-freq-hz", "--damping", "--tolerance-s", "--range-m-s2"):
        for v in ("0", "-1", "nan", "inf", "1e300", "-1e300"):
            cases.append(Case(["sync", g, opt, v], {2}, [opt]))
        cases.append(Case(["sync", g, opt, "abc"], {2}, [opt]))
    for noise in ("", "bogus", str(d / "no-such.h5"), str(d), str(bad["empty"]), str(bad["text"])):
        cases.append(Case(["calibrate", g, "--noise", noise], {2}, [noise or "--noise"]))
    cases.append(Case(["calibrate", g, "--json", str(d / "no-dir" / "x.json")], {1, 2}, ["no-dir"]))
    cases.append(Case(["apply-cal", g, "-o", g], {2}, [g]))
    cases.append(Case(["apply-cal", g, "-o", str(d / "no-dir" / "x.h5")], {2}, ["no-dir"]))
    for calname, text in (("empty.json", ""), ("garbage.json", "{not json"), ("list.json", "[1, 2]"),
                          ("nomodel.json", json.dumps({"results": {}}))):
        cp = d / calname
        cp.write_text(text)
        cases.append(Case(["apply-cal", g, "-o", str(out / "c.h5"), "--force", "--calibration", str(cp)], {2}, [str(cp)]))
    for cp in (d / "missing.json", d):
        cases.append(Case(["apply-cal", g, "-o", str(out / "c.h5"), "--force", "--calibration", str(cp)], {2}, [str(cp)]))
    cases.append(Case(["report", str(d / "no-such-run")], {2}, ["no-such-run"]))
    cases.append(Case(["report", str(d / "a-directory.h5")], {2}, ["a-directory.h5"]))

    # import: hostile CSV files and numbers
    csv_ok = d / "log.csv"
    t = np.arange(0, 60, 0.01)
    rows = "\n".join(f"{x:.2f},0.0,0.0,1.0,0.0,0.0,0.0" for x in t)
    csv_ok.write_text("time,ax,ay,az,gx,gy,gz\n" + rows + "\n")
    cols = "time=time,acc_x=ax,acc_y=ay,acc_z=az,gyr_x=gx,gyr_y=gy,gyr_z=gz"
    csvs = {"empty.csv": "", "header-only.csv": "time,ax,ay,az,gx,gy,gz\n",
            "nan.csv": "time,ax,ay,az,gx,gy,gz\n0,nan,0,1,0,0,0\n0.01,0,0,1,0,0,0\n",
            "text-value.csv": "time,ax,ay,az,gx,gy,gz\n0,x,0,1,0,0,0\n",
            "short-row.csv": "time,ax,ay,az,gx,gy,gz\n0,0,0\n",
            "time-backwards.csv": "time,ax,ay,az,gx,gy,gz\n1,0,0,1,0,0,0\n0,0,0,1,0,0,0\n",
            "binary.csv": "\x00\x01\x02garbage\xff"}
    for name, text in csvs.items():
        p = d / name
        p.write_text(text, errors="surrogateescape") if "\x00" not in text else p.write_bytes(text.encode("latin-1"))
        cases.append(Case(["import", str(p), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                           "--units", "acc=g,gyr=deg/s", "--rate", "100"], {2}, [str(p)]))
    for rate in ("0", "-100", "nan", "inf", "1e300", "abc"):
        cases.append(Case(["import", str(csv_ok), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                           "--units", "acc=g,gyr=deg/s", "--rate", rate], {2}, ["--rate", str(csv_ok)]))
    for units in ("", "acc=parsec", "acc=g", "gyr=deg/s,acc=counts:1/0 g"):
        cases.append(Case(["import", str(csv_ok), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                           "--units", units, "--rate", "100"], {2}, ["--units", "acc", "gyr"]))
    for badcols in ("", "acc_x=nope", "time=time", str(d / "no-map.yaml"), str(d / "empty.yaml")):
        cases.append(Case(["import", str(csv_ok), "-o", str(out / "imp.h5"), "--force", "--columns", badcols,
                           "--units", "acc=g,gyr=deg/s", "--rate", "100"], {2},
                          ["--columns", "column", str(csv_ok), badcols or "--columns"]))
    for sk in ("-1", "1000000"):
        cases.append(Case(["import", str(csv_ok), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                           "--units", "acc=g,gyr=deg/s", "--rate", "100", "--skip-rows", sk], {2},
                          ["--skip-rows", str(csv_ok)]))
    for gval in ("nan", "-9.8", "1e300"):
        cases.append(Case(["import", str(csv_ok), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                           "--units", "acc=g,gyr=deg/s", "--rate", "100", "--gravity", gval], {2}, ["--gravity"]))
    cases.append(Case(["import", str(d / "missing.csv"), "-o", str(out / "imp.h5"), "--force", "--columns", cols,
                       "--units", "acc=g,gyr=deg/s", "--rate", "100"], {2}, ["missing.csv"]))
    # -o a directory, even with --force: refused before any work (was exit 1 after the import,
    # 'Is a directory' from the rename of the finished file)
    cases.append(Case(["import", str(csv_ok), "-o", str(out), "--force", "--columns", cols,
                       "--units", "acc=g,gyr=deg/s", "--rate", "100"], {2}, [str(out)]))
    cases.append(Case(["apply-cal", g, "-o", str(out), "--force"], {2}, [str(out)]))

    # run / validate: hostile procedures, parameters and configs (nothing may be left behind)
    runs = tmp / "hostile-runs"
    procs = ROOT / "procedures"
    for verb in ("run", "validate"):
        extra = ["--out", str(runs)] if verb == "run" else []
        for name, (p, line) in ins.items():
            if name.startswith("cfg-"):
                continue
            where = f"{p}:{line}:" if line else str(p)
            cases.append(Case([verb, str(p), *extra], {2}, [where]))
        for p in (d / "no-such.yaml", d):
            cases.append(Case([verb, str(p), *extra], {2}, [str(p)]))
        for par in ("sampel=5 s", "sample=5 parsecs", "sample=-5 s", "sample=1e300 h", "sample=", "sample",
                    "=5 s", "sample=.nan", "warmup=[1, 2]", "discard=-1e-300 s", "warmup=32 days"):
            cases.append(Case([verb, str(procs / "24pos.yaml"), "-p", par, *extra], {2},
                              ["-p", "24pos.yaml", "warmup.yaml"]))
        for name, (p, line) in ins.items():
            if not name.startswith("cfg-"):
                continue
            devices = name in ("cfg-missing-serial.yaml", "cfg-refused-tcp.yaml", "cfg-unknown-host.yaml",
                               "cfg-not-a-tty.yaml")
            argv = [verb, str(procs / "warmup.yaml"), "--config", str(p), *extra]
            if devices:  # a valid config whose devices are not there: 1 for run (and validate --devices)
                if verb == "validate":
                    cases.append(Case(argv, {0}, []))
                    argv = [*argv, "--devices"]
                cases.append(Case(argv, {1}, ["/dev/ttyUSB97", "socket://127.0.0.1:9", "no-such-host",
                                              str(d / "empty.yaml")]))
            else:
                cases.append(Case(argv, {2}, [f"{p}:{line}:" if line else str(p)]))
        cases.append(Case([verb, str(procs / "warmup.yaml"), "--config", str(d / "no-config.yaml"), *extra], {2},
                          ["no-config.yaml"]))
    cases.append(Case(["validate", str(procs / "24pos.yaml"), "--devices"], {0}, []))
    # daemon client verbs with no daemon, resume of things that are not runs, sim with bad numbers
    sock = str(tmp / "no-daemon.sock")
    for verb in (["status"], ["queue"], ["pause"], ["abort"], ["logs"], ["resume"],
                 ["submit", str(procs / "warmup.yaml")], ["logs", "-n", "-5"]):
        cases.append(Case([*verb, "--socket", sock], {1, 2}, [sock, "-n"]))
    for run in (d / "no-such-run", d, good, base.parent):
        cases.append(Case(["resume", str(run), "--socket", sock, "--runs", str(tmp / "elsewhere")], {2}, [str(run)]))
    for speed in ("0", "-1", "nan", "inf", "1e300"):
        cases.append(Case(["sim", "up", "--speed", speed], {2}, ["--speed"]))
    cases.append(Case(["sim", "up", "--config", str(d / "cfg-empty.yaml")], {2}, ["cfg-empty.yaml"]))
    cases.append(Case(["no-such-command"], {2}, []))
    cases.append(Case([], {2}, []))

    # a closed stdout: every 7th case again with a stdout whose reader is gone (same exit code)
    closed = [Case(c.argv, c.expect, c.names, closed_stdout=True) for c in cases[::7]
              if c.argv and c.argv[0] not in ("run",)]
    return cases + closed, {"good": good, "runs": runs, "base": base}


def check(case: Case, o: Outcome) -> list[str]:
    """What is wrong with one outcome (empty when it is right)."""
    problems = []
    text = o.err
    if "Traceback" in text or "internal error" in text:
        problems.append("traceback / internal error on stderr")
    if o.warnings:
        problems.append(f"Python warnings: {o.warnings[:3]}")
    if o.code not in DOCUMENTED:
        problems.append(f"exit code {o.code} is not documented")
    elif o.code not in case.expect:
        problems.append(f"exit code {o.code}, expected {sorted(case.expect)}")
    if o.code != 0:
        lines = [ln for ln in text.splitlines() if ln.strip()]
        if not lines:
            problems.append("non-zero exit without a message")
        elif case.names and not any(n in text for n in case.names):
            problems.append(f"the message names none of {case.names}")
        if o.code in (1, 2) and case.argv and case.argv[0] in cli.COMMANDS | {"run": 0, "validate": 0}:
            prefix = f"rigctl {case.argv[0]}: "
            if not any(ln.startswith(prefix) for ln in lines) and not any(ln.startswith("usage:") for ln in lines):
                problems.append(f"no line starts with {prefix!r}")
    return problems


def test_the_whole_cli_under_hostile_input(tmp_path, request, monkeypatch):
    cases, fx = build_cases(tmp_path)
    # the Allan fit of identical curves once: the partial recordings (and the good one's
    # gx,ax octave cases) hold the same samples, so `rigctl allan --axes gx,ax` fits the same
    # curves of each (SharedWork: same arguments byte for byte)
    fits = SharedWork(allan_fit.fit_terms)
    monkeypatch.setattr(allan_fit, "fit_terms", fits)
    failures: list[str] = []
    t0 = time.monotonic()
    slowest: list[tuple[float, str]] = []
    by_code: dict[int, int] = {}
    for case in cases:
        try:
            o = run_case(case.argv, case.closed_stdout)
        except CaseTimeout as exc:
            failures.append(f"{case.argv}: HANG: {exc}")
            continue
        by_code[o.code] = by_code.get(o.code, 0) + 1
        slowest.append((o.seconds, " ".join(case.argv)))
        for p in check(case, o):
            failures.append(f"{case.argv}{' (closed stdout)' if case.closed_stdout else ''}: {p}\n"
                            f"    stderr: {o.err.strip()[-600:]}")
    wall = time.monotonic() - t0
    # a run or validate that never started leaves no run directory behind
    left = sorted(p.name for p in fx["runs"].glob("*")) if fx["runs"].exists() else []
    if left:
        failures.append(f"run directories left by runs that never started: {left}")
    slowest.sort(reverse=True)
    summary = [f"hostile-input CLI cases: {len(cases)} in {wall:.1f} s, exit codes "
               + ", ".join(f"{k}: {v}" for k, v in sorted(by_code.items()))
               + f"; failures: {len(failures)}; tracebacks: "
               + str(sum("traceback" in f for f in failures))
               + f"; Allan fits: {fits.calls}, {fits.hits} of them shared",
               "slowest: " + "; ".join(f"{s:.2f} s {a[:70]}" for s, a in slowest[:3])]
    request.node.user_properties.append(("rigctl_summary", summary))  # shown at the end (conftest)
    print("\n".join(summary))
    if os.environ.get("RIGCTL_HOSTILE_DUMP"):
        Path(os.environ["RIGCTL_HOSTILE_DUMP"]).write_text("\n".join(failures))
    assert len(cases) >= 1000, len(cases)
    assert not failures, f"{len(failures)} of {len(cases)} cases wrong:\n" + "\n".join(failures[:40])


# -- the in-process harness sees what a user sees -------------------------------------------------------
def test_subprocesses_match_the_in_process_harness(tmp_path):
    d = tmp_path / "h"
    d.mkdir()
    (d / "empty.h5").write_bytes(b"")
    (d / "text.h5").write_text("hello")
    bad_proc = d / "bad.yaml"
    bad_proc.write_text("steps:\n  - warmup:\n      duration: 15 parsecs\n")
    argvs = [["allan", str(d / "empty.h5")], ["calibrate", str(d / "text.h5")], ["sync", str(d)],
             ["validate", str(bad_proc)], ["validate", str(ROOT / "procedures" / "24pos.yaml"), "-p", "sampel=5 s"],
             ["allan", str(d / "missing.h5"), "--taus", "weekly"], ["report", str(d / "none")]]
    for argv in argvs:
        o = run_case(argv)
        r = subprocess.run([*rigctl_cmd(), *argv], capture_output=True, text=True, timeout=120, cwd=ROOT)
        assert (r.returncode, r.stderr) == (o.code, o.err), (argv, r.stderr, o.err)


def test_the_case_limit_counts_blocked_time_and_cpu(monkeypatch):
    """run_case's limit (here 1 s) catches a case blocked on a sleep, one blocked on a thread
    that sleeps, and a busy loop (by its CPU time), each within ~1 s of the limit."""
    monkeypatch.setitem(globals(), "CASE_LIMIT_S", 1.0)

    def blocked(argv):
        time.sleep(20)
        return 0

    def blocked_on_a_thread(argv):
        t = threading.Thread(target=time.sleep, args=(20,), daemon=True)
        t.start()
        t.join()
        return 0

    def busy(argv):
        t = time.monotonic()
        while time.monotonic() - t < 20:
            pass
        return 0

    for case in (blocked, blocked_on_a_thread, busy):
        monkeypatch.setattr(cli, "main", case)
        t0 = time.monotonic()
        try:
            run_case(["x"])
        except CaseTimeout as e:
            assert time.monotonic() - t0 < 5.0, (case.__name__, str(e))
            assert "no answer within 1 s" in str(e)
        else:
            raise AssertionError(f"{case.__name__}: no timeout")
