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
    /results/allan)}. test_allan_gm_real and
    test_allan_gm_fit both check this run (SHARED_FIXTURE_FILES: one worker makes it once)."""
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


# -- parallel runs: two phases ------------------------------------------------------------------
# pyproject's addopts start two pytest-xdist workers (-n 2 --dist loadfile) and pytest_xdist_make_scheduler
# below hands them _TwoPhaseScheduling: a test file is one unit of work (its module- and session-scoped
# fixtures are made once, as in a serial run). Phase 1: the files not in REALTIME_FILES run on both
# workers, the slowest first. Phase 2: once every phase-1 file has finished and the other worker has
# exited, the REALTIME_FILES run one after another on one worker, alone on the cores, as in a serial
# run: they keep deadlines in wall time (pty floods, 50x-500x rig clocks, kill -9 windows, HTTP
# load, browsers, terminals) and missed them with a second worker on a 2-core machine. `-n 0` runs
# everything serially; with the xdist plugin absent (-p no:xdist) the addopts fail, see README.

#: files that share an expensive session-scoped fixture of this conftest: one worker runs them all
SHARED_FIXTURE_FILES = {
    "tests/test_production_certificate.py": "full_calibration_run",
    "tests/test_report_sections.py": "full_calibration_run",
    "tests/test_report_html.py": "full_calibration_run",
    "tests/test_allan_gm_real.py": "mtig_gx_allan",
    "tests/test_allan_gm_fit.py": "mtig_gx_allan",
}

#: files whose tests keep deadlines in wall time: phase 2, one at a time, with no other test running.
#: A new test file on ptys, TCP devices, a scaled or real clock, subprocess daemons or wall-clock
#: waits belongs here; any file not listed runs beside another file in phase 1
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

#: phase-1 files by their CPU seconds (own + subprocesses) in a full run, largest first, so that the
#: two workers end together (116 s production_batch ... 28 s the full_calibration_run group); the
#: files not listed (under 15 s each) follow in collection order
PARALLEL_FIRST: tuple[str, ...] = tuple(f"tests/test_{name}.py" for name in (
    "production_batch", "cli_hostile", "cal_pose_loop_synth", "calibrate_correlated",
    "report_quickstart", "calibrate_emulated", "thermal", "daemon_procedures", "capture_memory",
    "allan_kalibr",
)) + ("full_calibration_run", "mtig_gx_allan")

try:
    from xdist.scheduler import LoadScopeScheduling
except ImportError:  # a venv installed before pytest-xdist joined the test extras
    LoadScopeScheduling = None

if LoadScopeScheduling is not None:
    class _TwoPhaseScheduling(LoadScopeScheduling):
        """--dist loadfile (with SHARED_FIXTURE_FILES as one unit) in two phases: the other files
        on every worker, then REALTIME_FILES on one worker alone.

        An xdist worker runs a test only once it holds the next one (or is told to shut down), so
        a worker counts as done only when it has exited: when the queue reaches the real-time
        units, each worker that asks for work is shut down (it runs the tests it holds and exits)
        while another one still takes work; the last one (``_rt``) gets the real-time units once
        all the others have been removed, so it holds at most one phase-1 test back meanwhile."""

        def __init__(self, config, log=None):
            super().__init__(config, log)
            self._rt = None

        def _split_scope(self, nodeid: str) -> str:
            path = nodeid.split("::", 1)[0]
            return SHARED_FIXTURE_FILES.get(path, path)

        @staticmethod
        def _realtime(scope: str) -> bool:
            return scope in REALTIME_FILES

        def _reschedule(self, node) -> None:
            if node.shutting_down:
                return
            if not self.workqueue:
                node.shutdown()
                return
            if self._pending_of(self.assigned_work[node]) > 2:
                return
            if not self._realtime(next(iter(self.workqueue))):
                self._assign_work_unit(node)
                return
            # phase 2: the last worker still taking work runs it; any other one finishes and exits
            if self._rt is None:
                if any(n is not node and not n.shutting_down for n in self.assigned_work):
                    node.shutdown()
                    return
                self._rt = node
            if node is not self._rt:
                node.shutdown()
                return
            if len(self.assigned_work) > 1:  # another worker is still finishing its phase-1 files
                return
            while self.workqueue and self._pending_of(self.assigned_work[node]) <= 2:
                self._assign_work_unit(node)

        def remove_node(self, node):
            crashitem = super().remove_node(node)
            if node is self._rt:
                self._rt = None  # crashed: the next worker to ask takes phase 2
                for other in list(self.assigned_work):
                    self._reschedule(other)
            elif self._rt is not None and self._rt in self.assigned_work:
                self._reschedule(self._rt)
            return crashitem

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
            order = sorted(units, key=lambda u: (self._realtime(u), rank.get(u, len(rank))))
            for scope in order:
                self.workqueue[scope] = units[scope]
            for _ in range(max(0, len(self.nodes) - len(self.workqueue))):
                unused, _ = self.assigned_work.popitem()
                unused.shutdown()
            for node in self.nodes:
                self._reschedule(node)
            for node in self.nodes:
                self._reschedule(node)

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_make_scheduler(config, log):
        return _TwoPhaseScheduling(config, log) if config.getoption("dist") == "loadfile" else None


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


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """The lines tests left for the summary (pytest_runtest_logreport)."""
    for line in _SUMMARY:
        terminalreporter.write_line(line)
