"""Shared pytest fixtures."""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
REF_DATA = ROOT / "tests" / "data"


@pytest.fixture(scope="session")
def ref_data() -> Path:
    """Path to tests/data: real data and reference results from other labs (README there)."""
    return REF_DATA


@pytest.fixture(scope="session")
def full_calibration_run(tmp_path_factory) -> tuple[Path, str]:
    """A short emulated full calibration run once per session as ``rigctl run`` (a subprocess):
    its solve steps calibrate and write the report. Returns (run directory, stdout)."""
    from helpers import run_rigctl

    out = tmp_path_factory.mktemp("runs")
    r = run_rigctl("run", "procedures/full-calibration.yaml", "-p", "warmup=1 min", "-p", "sample=5 s",
                   "--out", str(out), timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return next(out.glob("*-full-calibration")), r.stdout


@pytest.fixture(scope="session")
def mtig_gx_allan(ref_data, tmp_path_factory) -> dict:
    """The real MTi-G gyro's x axis (tests/data/mtig-static-contaminated, 1.39 h at 100 Hz)
    through `rigctl import` + `rigctl allan --db none --json` in process, once per session:
    {"y": the rates, "text": allan's stdout, "res": the JSON's axes.gx, "ind": the independent
    white + GM read (test_allan_gm_real.independent_fit), "rec": the recording (with allan's
    /results/allan; a test that analyses it again does so on a copy,
    helpers.copy_recording)}. test_allan_gm_real, test_allan_gm_fit and test_allan_gm all check
    this run (SHARED_FIXTURE_FILES: one worker makes it once)."""
    import io
    import json
    from contextlib import redirect_stderr, redirect_stdout

    import numpy as np

    from rigctl import cli
    from test_allan_gm_real import independent_fit

    d = ref_data / "mtig-static-contaminated"
    if not d.exists():
        pytest.skip(f"{d} not present (a commercial redistribution leaves it out: CC BY-NC-SA "
                    "4.0, see its README)")

    def rigctl(*argv: str) -> str:
        out, err = io.StringIO(), io.StringIO()
        with redirect_stdout(out), redirect_stderr(err):
            code = cli.main(list(argv))
        assert code == 0, err.getvalue()[-2000:]
        return out.getvalue()

    y = np.loadtxt(d / "gyro_x_rad_s.txt.gz")
    tmp = tmp_path_factory.mktemp("mtig_gm")
    txt, rec, js = tmp / "mtig.txt", tmp / "mtig.h5", tmp / "mtig.json"
    np.savetxt(txt, y, fmt="%.8g")  # the file's own 8 significant digits: the same numbers
    rigctl("import", str(txt), "-o", str(rec), "--rate", "100", "--columns", "gyr_x=0",
           "--units", "gyr=rad/s")
    text = rigctl("allan", str(rec), "--db", "none", "--json", str(js))
    return {"y": y, "text": text, "res": json.loads(js.read_text())["axes"]["gx"],
            "ind": independent_fit(y), "rec": rec}


@pytest.fixture(scope="session")
def declared_only_hour(tmp_path_factory) -> tuple[Path, dict]:
    """One hour at rest, 100 Hz, of the emulator's declared_only profile with test_noise_coefficients'
    GYRO and ACCEL coefficients (the profile's B, per-axis N, K ten times the profile's so that
    the hour resolves it), recorded once per session (helpers.emulated_capture, seed 11): (the
    recording, its /truth's imu). test_noise_coefficients and test_allan_kalibr both analyse it,
    each on its own copy (SHARED_FIXTURE_FILES: one worker makes it once)."""
    from helpers import emulated_capture
    from rigctl.solvers.noise_coefficients import to_config
    from test_noise_coefficients import ACCEL, GYRO, PROCEDURE

    return emulated_capture(tmp_path_factory.mktemp("declared_only_hour"), {
        "profile": "declared_only", "overrides": {"gyro": {"noise": to_config(GYRO, "gyro")},
                                                  "accel": {"noise": to_config(ACCEL, "accel")}}}, PROCEDURE)


@pytest.fixture(scope="session")
def declared_only_hour_allan(declared_only_hour, tmp_path_factory) -> tuple[Path, dict, Path]:
    """declared_only_hour analysed once per session: `rigctl allan REC --kalibr imu.yaml --json
    allan.json --csv allan.csv --db none` (in process, helpers.rigctl_in_process) on a copy of the
    recording. (the analysed recording, with /results/allan; its /truth's imu; the directory of
    imu.yaml, allan.json and allan.csv). test_allan_kalibr checks the exports, test_noise_coefficients
    the stored /results/allan and the noise model calibrate takes from it; each copies what it
    reads (helpers.copy_recording), so no test sees what another wrote."""
    from helpers import copy_recording, rigctl_in_process

    out = tmp_path_factory.mktemp("declared_only_hour_allan")
    rec = copy_recording(declared_only_hour[0], out)
    r = rigctl_in_process("allan", str(rec), "--kalibr", str(out / "imu.yaml"), "--json",
                          str(out / "allan.json"), "--csv", str(out / "allan.csv"), "--db", "none")
    assert r.returncode == 0, r.stderr[-2000:]
    return rec, declared_only_hour[1], out


@pytest.fixture
def sock_dir():
    """A fresh directory under /tmp, removed afterwards: short enough for the AF_UNIX socket
    paths of a daemon (<= 107 bytes; pytest's tmp_path can be longer)."""
    base = Path(tempfile.mkdtemp(prefix="rigctl-wire-", dir="/tmp"))
    try:
        yield base
    finally:
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture
def small_fs(tmp_path):
    """A 6 MiB tmpfs (a disk that fills up); skips unless this process may mount one (root)."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=6m", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"mount -t tmpfs is not permitted here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# -- parallel runs: a real-time worker and background workers --------------------------------------
# pyproject's addopts start three pytest-xdist workers (-n 3 --dist loadfile) and pytest_xdist_make_scheduler
# below hands them _RealtimeFirstScheduling: a test file is one unit of work (its module- and
# session-scoped fixtures are made once, as in a serial run). The first worker (gw0, the real-time
# worker) runs the REALTIME_FILES first, one after another, at normal priority; they keep deadlines in
# wall time (pty floods, 50x-500x rig clocks, kill -9 windows, HTTP load, browsers, terminals). Every
# other worker runs the other files meanwhile at background priority (_background_priority: its own
# session and autogroup at nice 19, SCHED_IDLE, idle I/O class), so that it takes only the CPU time
# the real-time tests leave unused: with a second worker at normal priority those tests missed their
# deadlines on a 2-core machine, and with them alone on the cores (the previous scheme) a core sat
# idle for the ~12 minutes they take. Two background workers on two cores: the real-time tests
# wait (on sockets, ptys, sleeps, their daemons) for part of their time, and with one background
# worker that time was lost -- 180 % of the two cores busy in the clean-clone CI at ea637c5, 250
# core-seconds idle. Once the real-time files are done gw0 takes the other files too. `-n 0` runs everything serially; with the xdist plugin absent (-p no:xdist) the addopts fail,
# see README.

#: files that share an expensive session-scoped fixture of this conftest: one worker runs them all
SHARED_FIXTURE_FILES = {
    "tests/test_production_certificate.py": "full_calibration_run",
    "tests/test_report_sections.py": "full_calibration_run",
    "tests/test_report_html.py": "full_calibration_run",
    "tests/test_allan_gm_real.py": "mtig_gx_allan",
    "tests/test_allan_gm_fit.py": "mtig_gx_allan",
    "tests/test_allan_gm.py": "mtig_gx_allan",
    "tests/test_noise_coefficients.py": "declared_only_hour",
    "tests/test_allan_kalibr.py": "declared_only_hour",
}

#: files whose tests keep deadlines in wall time: one at a time on the real-time worker, with only
#: background-priority work beside them. A new test file on ptys, TCP devices, a scaled or real
#: clock, subprocess daemons or wall-clock waits belongs here; any file not listed runs on either
#: worker
REALTIME_FILES = frozenset(f"tests/test_{name}.py" for name in (
    # subprocess daemons, scaled clocks, kill -9, HTTP load, a browser, notifications
    "daemon_analysis_interrupt", "daemon_control", "daemon_crash", "daemon_http_browser", "daemon_http_load",
    "daemon_notify", "daemon_wire", "daemon_wire_config", "daemon_wire_disk", "daemon_wire_memory",
    "daemon_wire_serve",
    # emulated devices on ptys and TCP at 50x-500x, byte floods, hardware-in-the-loop runs
    "wire_acl", "wire_imu_errors", "wire_modbus", "wire_novatel", "wire_vectornav",
    "wire_xsens_identity", "wire_xsens_server", "hil_faults", "hil_pulses_config", "hil_runs",
    "thermal_wire", "hil_time_offsets", "hil_power_cycle", "pty_host_stall", "slow_stream_pace", "link_loss_order",
    "safe_state_slow_table",
    # terminals (pty, tmux), scaled-clock runs with wall-clock limits, concurrent database writers
    "cli", "cli_console", "report_tmux", "results_db_concurrency", "engine_latency",
    # the in-process emulator on a scaled clock: a catch-up longer than 0.05 s of wall time sets
    # the clock back (sim/world.py ADVANCE_BUDGET_WALL_S), and the file asserts none at 5x, a
    # SIGTERM answered within 10 s and no poll longer than 2 s, all in wall time
    "run_fast_clock", "sim_speed",
))
# Not here, though they run a daemon or resume runs: test_daemon_http (an in-process daemon on
# configs/sim.yaml's virtual clock, HTTP on loopback; its waits, up to 90 s for a 24-position
# job, guard against hangs and are no deadlines) and test_runner_identity (in-process runs and
# resumes in virtual time, a daemon's refused resume job): CPU only.

_missing = sorted(f for f in REALTIME_FILES if not (ROOT / f).is_file())
assert not _missing, f"REALTIME_FILES names files that do not exist: {_missing}"

#: the other files by their CPU seconds (own + subprocesses) in a full run, largest first, so that
#: the workers end together (116 s production_batch ... 28 s the full_calibration_run group); the
#: files not listed (under 15 s each) follow in collection order
PARALLEL_FIRST: tuple[str, ...] = tuple(f"tests/test_{name}.py" for name in (
    "production_batch", "cli_hostile", "cal_pose_loop_synth", "calibrate_correlated",
    "report_quickstart", "calibrate_emulated", "thermal", "daemon_procedures", "capture_memory",
)) + ("declared_only_hour", "full_calibration_run", "mtig_gx_allan")

try:
    from xdist.scheduler import LoadScopeScheduling
except ImportError:  # a venv installed before pytest-xdist joined the test extras
    LoadScopeScheduling = None

#: the xdist worker that runs REALTIME_FILES at normal priority
REALTIME_WORKER = "gw0"

if LoadScopeScheduling is not None:
    class _RealtimeFirstScheduling(LoadScopeScheduling):
        """--dist loadfile (with SHARED_FIXTURE_FILES as one unit): the REALTIME_FILES on the
        real-time worker first, the other files (PARALLEL_FIRST's order) on every worker.

        An xdist worker runs a test only once it holds the next one (or is told to shut down), so
        each worker is kept at most two tests ahead. If the real-time worker goes (a crash), the
        next worker that asks for work takes the remaining real-time files."""

        def __init__(self, config, log=None):
            super().__init__(config, log)
            self._rt_node = None  # the worker that runs the real-time files (None: not chosen yet)

        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return SHARED_FIXTURE_FILES.get(path, path)

        def _reschedule(self, node) -> None:
            if node.shutting_down or self._pending_of(self.assigned_work[node]) > 2:
                return
            rt = next((u for u in self.workqueue if u in REALTIME_FILES), None)
            if rt is not None and self._rt_node is None:
                # gw0 while it lives; after a crash, whichever worker asks first
                named = [n for n in self.assigned_work if n.gateway.id == REALTIME_WORKER]
                self._rt_node = named[0] if named else node
            unit = rt if node is self._rt_node and rt is not None else \
                next((u for u in self.workqueue if u not in REALTIME_FILES), None)
            if unit is None:
                node.shutdown()
                return
            self.workqueue.move_to_end(unit, last=False)  # the unit _assign_work_unit takes
            self._assign_work_unit(node)

        def remove_node(self, node):
            if node is self._rt_node:
                self._rt_node = None  # crashed (or done): the next worker to ask takes what is left
            return super().remove_node(node)  # (it reschedules the other workers)

        def schedule(self) -> None:
            assert self.collection_is_completed
            if self.collection is not None:
                for node in self.nodes:
                    self._reschedule(node)
                return
            if not self._check_nodes_have_same_collection():
                self.log("**Different tests collected, aborting run**")
                return
            self.collection = list(next(iter(self.registered_collections.values())))
            if not self.collection:
                return
            units: dict[str, dict[str, bool]] = {}
            for nodeid in self.collection:
                units.setdefault(self._split_scope(nodeid), {})[nodeid] = False
            rank = {f: i for i, f in enumerate(PARALLEL_FIRST)}
            for scope in sorted(units, key=lambda u: rank.get(u, len(rank))):
                self.workqueue[scope] = units[scope]
            for node in self.nodes:
                self._reschedule(node)
            for node in self.nodes:
                self._reschedule(node)

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_make_scheduler(config, log):
        return _RealtimeFirstScheduling(config, log) if config.getoption("dist") == "loadfile" else None


def _background_priority() -> list[str]:
    """Put this process (a background xdist worker) and the processes it starts at background
    priority: a session of its own, whose autogroup gets nice 19 (with the kernel's autogroups on,
    CPU time is shared between sessions first, so SCHED_IDLE alone would still take half the cores
    from a daemon the real-time worker starts in its own session), the SCHED_IDLE policy within it,
    and the idle I/O class. Returns what could not be done (each step is independent)."""
    failed = []
    try:
        os.setsid()
    except OSError as e:
        failed.append(f"setsid: {e}")
    try:
        with open("/proc/self/autogroup", "w") as fh:
            fh.write("19")
    except OSError as e:
        failed.append(f"autogroup nice: {e}")
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (OSError, AttributeError) as e:
        failed.append(f"SCHED_IDLE: {e}")
    try:
        r = subprocess.run(["ionice", "-c", "3", "-p", str(os.getpid())], capture_output=True, text=True)
        if r.returncode:
            failed.append(f"ionice: {r.stderr.strip()}")
    except OSError as e:
        failed.append(f"ionice: {e}")
    return failed


#: the source trees of the installed package (pyproject's package-dir: rigctl, rigctl.drivers,
#: rigctl.sim); an editable install leaves them uncompiled
PACKAGE_SOURCES = ("rigctl", "drivers", "sim")


def pytest_configure(config):
    """Compile the package's modules to ``__pycache__`` once, before the workers start.

    With PYTHONDONTWRITEBYTECODE set (this machine's environment, and so CI's) no process keeps
    the bytecode it compiles: every xdist worker and every ``rigctl`` subprocess the tests start
    (several hundred) compiled the ~48,000 lines of rigctl/, sim/ and drivers/ it imports again,
    ~0.2 s of CPU per ``rigctl run`` / ``calibrate`` (1.60 -> 1.38 s user for their imports,
    measured). The variable only stops the writing: a valid .pyc beside the source is read.
    compileall checks each source's mtime and size as the import system does, so an edited file
    is compiled again here (or, if this fails, e.g. a read-only tree, in each process as before)."""
    if hasattr(config, "workerinput"):  # an xdist worker: the controller did it
        if config.workerinput.get("rigctl_background"):  # pytest_configure_node
            config.workeroutput["background_priority_failed"] = _background_priority()
        return
    import compileall

    for name in PACKAGE_SOURCES:
        compileall.compile_dir(str(ROOT / name), quiet=2)
    _cache_test_modules(config)


#: processes that rewrite the test modules' asserts in _cache_test_modules (the CI machine's cores)
REWRITE_PROCESSES = 2


def _rewrite_into_cache(paths: list[str]) -> None:
    """pytest's assertion rewrite of ``paths`` into the pyc cache pytest reads (a forked child of
    _cache_test_modules: ``_REWRITE_CONFIG`` is the parent's config)."""
    from _pytest.assertion.rewrite import PYC_TAIL, _rewrite_test, _write_pyc, assertstate_key, get_cache_dir

    config = _REWRITE_CONFIG
    state = config.stash[assertstate_key]
    try:
        for p in map(Path, paths):
            cache = get_cache_dir(p)
            cache.mkdir(exist_ok=True)
            source_hash, co = _rewrite_test(p, config)
            _write_pyc(state, co, source_hash, cache / (p.name[:-3] + PYC_TAIL))
    except Exception:  # noqa: BLE001 - e.g. a syntax error: the import reports it, as without the cache
        os._exit(1)
    os._exit(0)  # no atexit or pytest teardown in the forked child


_REWRITE_CONFIG = None


def _cache_test_modules(config) -> None:
    """Rewrite and compile tests/ once in the controller, before the workers collect.

    pytest rewrites the asserts of every test module it imports (an AST pass in Python: ~19 s of
    CPU for the ~200 files here) and caches the result beside the module, but not when bytecode
    writing is off (PYTHONDONTWRITEBYTECODE, CI's environment): each xdist worker rewrote all of
    them again at collection, 28.9 s of CPU for `pytest --collect-only` against 9.4 s with the
    cache (measured). Here the test modules are rewritten into pytest's own cache
    (tests/__pycache__/*-pytest-*.pyc, keyed by the source's hash, so an edited file is rewritten
    again at import) by REWRITE_PROCESSES forked processes, and the helper modules the tests
    import (helpers.py, hil_support.py, ...) are compiled. The workers then read the cache as a
    second run of pytest does. Anything that fails here (a read-only tree, another pytest's
    internals) leaves the workers rewriting as before: the same tests run either way."""
    global _REWRITE_CONFIG
    import compileall
    import multiprocessing
    import sys

    tests = ROOT / "tests"
    if not sys.dont_write_bytecode or config.getoption("assertmode", "rewrite") != "rewrite":
        return  # pytest keeps its own cache (or does not rewrite)
    if config.getoption("dist", "no") == "no" or config.args_source != pytest.Config.ArgsSource.TESTPATHS:
        return  # no workers, or the files named on the command line only: rewritten as imported
    try:
        from _pytest.assertion.rewrite import assertstate_key
        config.stash[assertstate_key]
    except (ImportError, KeyError):
        return
    mods = sorted(tests.glob("*.py"))
    rewritten = [str(p) for p in mods if p.name.startswith("test_") or p.name == "conftest.py"]
    for p in mods:
        if str(p) not in rewritten:
            compileall.compile_file(str(p), quiet=2)
    _REWRITE_CONFIG = config
    try:
        ctx = multiprocessing.get_context("fork")
        # the largest files first, dealt out in turn: the processes end together
        rewritten.sort(key=lambda f: -os.path.getsize(f))
        procs = [ctx.Process(target=_rewrite_into_cache, args=(rewritten[i::REWRITE_PROCESSES],))
                 for i in range(REWRITE_PROCESSES)]
        for pr in procs:
            pr.start()
        for pr in procs:
            pr.join()
    except (OSError, ValueError):
        pass
    finally:
        _REWRITE_CONFIG = None


_SUMMARY: list[str] = []


def pytest_runtest_logreport(report):
    """Collect the lines a test left in its ``user_properties`` under ``rigctl_summary`` (e.g. the
    hostile-input case count); they travel with the report from an xdist worker."""
    if report.when == "call":
        _SUMMARY.extend(line for key, lines in report.user_properties if key == "rigctl_summary"
                        for line in lines)


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """With _RealtimeFirstScheduling (--dist loadfile), every worker but the real-time one runs
    at background priority (its pytest_configure, _background_priority)."""
    node.workerinput["rigctl_background"] = (node.config.getoption("dist") == "loadfile"
                                             and node.gateway.id != REALTIME_WORKER)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """A background worker that could not lower its priority says so in the summary: the
    real-time tests then had a competitor on the cores."""
    failed = getattr(node, "workeroutput", {}).get("background_priority_failed")
    if failed:
        _SUMMARY.append(f"background worker {node.gateway.id}: priority not fully lowered ({'; '.join(failed)})")


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The lines tests left for the summary (pytest_runtest_logreport)."""
    for line in _SUMMARY:
        terminalreporter.write_line(line)
