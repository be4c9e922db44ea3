"""Report sections: what each shows, "Not run" when its results are absent, the numbers and
units it prints, the quick Allan curve, the sync clock residual, the hook and missing
matplotlib (issue 9). The Chromium rendering is in tests/test_report_html.py."""
from __future__ import annotations

import html.parser
import json
import math
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from helpers import run_rigctl
from recording_helpers import write_recording

pytest.importorskip("matplotlib")

from rigctl.report import report, report_build, report_html  # noqa: E402
from rigctl.recording.recorder import write_results  # noqa: E402

G0 = 9.80665


class Page(html.parser.HTMLParser):
    """Per section: img ids -> src, "Not run" texts, table rows (cell texts)."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.sec: str | None = None
        self.imgs: dict[str, dict[str, str]] = {}
        self.not_run: dict[str, str] = {}
        self.rows: dict[str, list[list[str]]] = {}
        self.external: list[str] = []
        self._cell: list[str] | None = None
        self._row: list[str] | None = None
        self._p_not_run = False
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        for key in ("src", "href"):
            v = a.get(key) or ""
            if v and not v.startswith(("data:", "#")):
                self.external.append(v)
        if tag in ("link", "script", "iframe", "object"):
            self.external.append(tag)
        if tag == "section":
            self.sec = a.get("id")
            self.imgs[self.sec] = {}
            self.rows[self.sec] = []
        elif tag == "img" and self.sec:
            self.imgs[self.sec][a.get("id", "")] = a.get("src", "")
        elif tag == "tr":
            self._row = []
        elif tag in ("td", "th"):
            self._cell = []
        elif tag == "p" and "not-run" in (a.get("class") or ""):
            self._p_not_run = True
            self.not_run[self.sec] = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._row is not None and self._cell is not None:
            self._row.append("".join(self._cell).strip())
            self._cell = None
        elif tag == "tr" and self._row is not None and self.sec:
            self.rows[self.sec].append(self._row)
            self._row = None
        elif tag == "p":
            self._p_not_run = False

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)
        if self._p_not_run:
            self.not_run[self.sec] += data


def _check_page(page: Page) -> None:
    assert not page.external, f"external resources: {page.external[:3]}"
    assert [s for s, _ in report_html.SECTIONS] == list(page.imgs)
    for sec, imgs in page.imgs.items():
        for pid, src in imgs.items():
            assert pid.startswith("plot-") and src.startswith("data:image/png;base64,"), (sec, pid)


@pytest.fixture
def calibrated(full_calibration_run) -> Path:
    """The session's short emulated full calibration (tests/conftest.py)."""
    return full_calibration_run[0]


def test_calibration_sections_show_the_fit_in_field_units(calibrated: Path) -> None:
    # written by the procedure's last solve step (report), after the calibration's
    page = Page((calibrated / "report.html").read_text())
    _check_page(page)
    with h5py.File(calibrated / "recording.h5", "r") as f:
        payload = json.loads(f["results/calibration"].attrs["json"])
        truth = json.loads(f["truth"].attrs["params_json"])
        n_seg = int(sum(k in (b"orientation", b"rate") for k in f["segments/kind"][()]))
    cl = report.find_session(payload)["closed_loop"]
    if "calibration" not in page.not_run:
        assert {"plot-cal_residuals_orientation", "plot-cal_residuals_rate"} <= set(page.imgs["calibration"])
        assert "plot-cal_rms" in page.imgs["closed-loop"]
        # residuals map one row per orientation / rate segment, six channels
        assert len(cl["declared"]["residuals"]) == 6 * n_seg
        # parameters: SI names turned into field units, value and interval scaled exactly
        rows: dict[str, list[str]] = {}
        for row in page.rows["calibration"]:  # the first table: the closed-loop model
            if row:
                rows.setdefault(row[0], row)
        fin = {p["name"]: p for p in cl["final"]["parameters"]}
        # columns: parameter, unit, value, 1-sigma, [95 % low, high], k, dof; the value rounded to
        # the uncertainty's second significant digit (so within 0.05 of its 1-sigma)
        def close(row: list[str], exact: float, col: int = 2) -> bool:
            return abs(float(row[col]) - exact) <= 0.051 * float(row[3])

        for i, ax in enumerate("xyz"):
            shown = rows[f"accel_bias_{ax}"]
            assert shown[1] == "mg"
            p = fin[f"accel_bias_{ax}_m_s2"]
            assert close(shown, p["value"] * 1000 / G0)
            lo, hi = (float(x) for x in shown[4].strip("[]").split(","))
            assert abs(lo - p["ci95_low"] * 1000 / G0) <= 0.051 * float(shown[3])
            # the emulator's true bias (mg) lies in the printed 95 % interval (seed 1)
            assert lo <= truth["imu"]["accel_bias_m_s2"][i] * 1000 / G0 <= hi
            g = rows[f"gyro_bias_{ax}"]
            assert g[1] == "deg/h" and close(g, fin[f"gyro_bias_{ax}_rad_s"]["value"] * 180 / math.pi * 3600)
            # scale errors in ppm as `rigctl calibrate` prints them: (M_ii - 1) * 1e6
            sc = rows[f"accel_scale_error_{ax}"]
            m_ii = fin[f"accel_M_{ax}{ax}_ratio"]
            assert sc[1] == "ppm" and close(sc, (m_ii["value"] - 1.0) * 1e6)
            true_ppm = (truth["imu"]["accel_matrix"][i][i] - 1.0) * 1e6
            lo_s, hi_s = (float(x) for x in sc[4].strip("[]").split(","))
            assert lo_s <= true_ppm <= hi_s
        # the chain: one table row per explain entry (+ header)
        cl_rows = page.rows["closed-loop"]
        head = cl_rows.index(["round", "residual pattern", "candidate", "statistic", "decision"])
        chain = [row for row in cl_rows[head + 1:] if len(row) == 5]
        assert [row[2] for row in chain] == [x["candidate"] for x in cl["explain"]]
        assert [row[4] for row in chain] == [x["decision"] for x in cl["explain"]]
        ba = {row[0]: row for row in page.rows["closed-loop"] if row}
        for t in cl["rms_table"]:
            if t["channel"] != "all":
                u = t["unit"]
                assert float(ba[t["channel"]][3]) == pytest.approx(t[f"rms_before_{u}"], rel=1e-4)
                assert float(ba[t["channel"]][2]) == pytest.approx(t[f"rms_raw_{u}"], rel=1e-4)
    else:
        assert "/results/calibration" in page.not_run["calibration"]
    # no Allan or sync in a full calibration: those sections say so, with what to run
    assert "rigctl allan" in page.not_run["allan"] and not page.imgs["allan"]
    assert "rigctl sync" in page.not_run["sync"] and not page.imgs["sync"]
    assert "plot-table_timeline" in page.imgs["table"]
    prov = {row[0]: row[1] for row in page.rows["provenance"] if len(row) == 2}
    assert prov["procedure_name"] == "full-calibration" and prov["run status"] == "complete"
    assert json.loads(prov["parameters_json"])["warmup"] == "1 min"  # the -p value of the run (conftest)
    assert "numpy" in prov and "h5py" in prov  # versions table


RATE = 100.0


def test_calibration_names_each_axis_one_way(full_calibration_run) -> None:
    """The new-user audit: `rigctl calibrate` named the channels accel_x ... gyro_z while rigctl
    allan and the recording format say ax ... gz. Text, JSON and the HTML report now use the
    one spelling (rigctl.sensor_axes; docs/data-format.md, "Axis names")."""
    import re

    run_dir, stdout = full_calibration_run
    axes = ["ax", "ay", "az", "gx", "gy", "gz"]
    old = re.compile(r"\b(?:accel|gyro|acc|gyr)_[xyz]\b|\b(?:accelerometer|gyro) [xyz]\b")
    assert not old.search(stdout), old.search(stdout)
    assert [ln.split()[0] for ln in stdout.splitlines() if re.match(r"  [ag][xyz] +N ", ln)] == axes
    with h5py.File(run_dir / "recording.h5", "r") as f:
        text = f["results/calibration"].attrs["json"]
    payload = json.loads(text)
    assert not old.search(text), old.search(text)
    cl = report.find_session(payload)["closed_loop"]
    assert [t["channel"] for t in cl["rms_table"]] == [*axes, "all"]
    page = (run_dir / "report.html").read_text()
    assert not old.search(page), old.search(page)
    rows = {row[0] for row in Page(page).rows["closed-loop"] if row}
    assert set(axes) <= rows, rows


@pytest.fixture(scope="module")
def tap_recording(tmp_path_factory) -> Path:
    """A tap session (emulated), written as a minimal recording, synchronised by rigctl sync."""
    from rigctl.sim import taps

    sched = taps.ScheduleParams((20.0, 200.0), 10, (1.0, 3.0))
    params = taps.TapParams(response="second_order", jitter_s=2e-4, missed_count=1, spurious_spikes=1)
    s = taps.simulate_taps(RATE, 240.0, sched, params, taps.ClockParams(offset_s=0.2, drift_ppm=60.0),
                           random_dropouts=1, dropout_length=32, seed=5)
    path = tmp_path_factory.mktemp("taps") / "taps.h5"
    gyro = np.random.default_rng(5).normal(0.0, 1e-3, (s.counter.size, 3))  # white gyro noise
    write_recording(path, RATE, counter=s.counter, specific_force=s.specific_force, angular_rate=gyro,
                    pulses={"time": s.pulse_time})
    r = run_rigctl("sync", str(path))
    assert r.returncode == 0, r.stderr
    return path


def test_allan_quick_curve_when_the_results_lack_arrays(tap_recording: Path, tmp_path: Path) -> None:
    rec = tmp_path / "recording.h5"
    shutil.copy(tap_recording, rec)
    write_results(rec, "allan", {"axes": {"gz": {"sensor": "gyro"}}})  # summary only, no curves
    out = report_build.build_report(rec, tmp_path / "rep")
    page = Page(out.read_text())
    _check_page(page)
    assert "plot-allan" in page.imgs["allan"] and "allan" not in page.not_run
    assert "quick" in out.read_text()
    data = report.load_run(rec)
    from rigctl.report.report_allan import allan_curves
    from rigctl.solvers import allan as A

    cv = allan_curves(data)["gz"]
    assert cv["quick"] and cv["unit"] == "deg/h"
    with h5py.File(rec, "r") as f:
        w = f["imu/angular_rate"][:, 2]
        counter = f["imu/counter"][()].astype(np.int64)
        fs = float(f["imu"].attrs["sample_rate_hz"])
    # the smallest tau against the exact overlapping ADEV of the raw gyro z, in deg/h, with the
    # recording's dropout skipped as Stable32 does: every gap-free stretch (counter steps of 1)
    # contributes its own second differences of the phase; sums and term counts are added
    m = int(round(cv["tau_s"][0] * fs))
    cuts = np.flatnonzero(np.diff(counter) != 1) + 1
    assert cuts.size == 1  # the fixture's one dropout of 32 samples
    ss, nt = 0.0, 0
    for part in np.split(w, cuts):
        x = np.concatenate([[0.0], np.cumsum(part)]) / fs
        d = x[2 * m:] - 2 * x[m:-m] + x[: -2 * m]
        ss, nt = ss + float(np.sum(d * d)), nt + d.size
    ref = math.sqrt(ss / (2.0 * nt * (m / fs) ** 2))
    assert cv["adev"][0] == pytest.approx(ref * 180 / math.pi * 3600, rel=1e-9)
    # the whole series bridged across the dropout would differ (the old, silent behaviour)
    bridged = float(A.oadev(w, 1.0 / fs, [m]).dev[0]) * 180 / math.pi * 3600
    assert abs(cv["adev"][0] / bridged - 1) > 1e-6
    assert np.all(cv["lo95"] <= cv["adev"]) and np.all(cv["adev"] <= cv["hi95"])


def test_sync_plots_and_the_clock_residual(tap_recording: Path, tmp_path: Path) -> None:
    from rigctl.analysis import sync

    rec = tmp_path / "taps.h5"
    shutil.copy(tap_recording, rec)
    out = report_build.build_report(rec, tmp_path)
    page = Page(out.read_text())
    _check_page(page)
    assert {"plot-sync_hist", "plot-sync_residual"} <= set(page.imgs["sync"])
    for sec in ("table", "calibration", "closed-loop", "allan"):
        assert sec in page.not_run, sec
    # the report's clock at each tap equals the sync pipeline's own clock model
    data = report.load_run(rec)
    arr = data.results["sync"]["arrays"]
    with h5py.File(rec, "r") as f:
        counter, sf = f["imu/counter"][()], f["imu/specific_force"][:, 2]
        pulses = f["pulses/time"][()]
    res = sync.synchronise(counter, sf, RATE, pulses)
    m = res.match
    want = res.clock.time_of_counter(res.tap_time_s[m.tap_index] * RATE)
    assert np.max(np.abs(arr["tap_reference_time"] - want)) < 1e-9
    err_ms = (arr["pulse_time"] - arr["tap_reference_time"]) * 1e3
    inl = arr["inlier"].astype(bool)
    assert np.std(err_ms[inl], ddof=1) == pytest.approx(
        data.results["sync"]["json"]["residual_std_ms"], rel=0.05)
    assert data.imu["dropped"] == 32 and data.imu["gaps"] == 1
    summary = {row[0]: row[1] for row in page.rows["summary"] if len(row) == 2}
    assert summary["dropped samples (counter gaps)"] == "32 in 1 gaps"


def test_orientation_free_calibration_has_tables_but_no_closed_loop(tap_recording: Path,
                                                                   tmp_path: Path) -> None:
    from rigctl.solvers.calibration_result import fit_linear

    rng = np.random.default_rng(3)
    x = rng.normal(size=(12, 2))
    fit = fit_linear(x, x @ [0.01, -0.02] + 1e-3 * rng.normal(size=12), np.full(12, 1e-3),
                     ["accel_bias_x_m_s2", "gyro_bias_z_rad_s"], method="multipos_accel")
    rec = tmp_path / "taps.h5"
    shutil.copy(tap_recording, rec)
    write_results(rec, "calibration", {"mode": "orientation_free", "trustworthy": False,
                                       "status": "NOT TRUSTWORTHY", "reasons": ["6 poses: too few"],
                                       "results": {"multipos_accel": fit.to_dict()}})
    page = Page(report_build.build_report(rec, tmp_path).read_text())
    assert "calibration" not in page.not_run and "closed-loop" in page.not_run
    rows = {row[0]: row for row in page.rows["calibration"] if row}
    for name, unit, exact in (("accel_bias_x", "mg", fit.values[0] * 1000 / G0),
                              ("gyro_bias_z", "deg/h", fit.values[1] * 180 / math.pi * 3600)):
        assert rows[name][1] == unit and abs(float(rows[name][2]) - exact) <= 0.051 * float(rows[name][3])
    assert "NOT TRUSTWORTHY" in (tmp_path / "report.html").read_text()


def test_solve_hook_writes_beside_the_recording(tap_recording: Path, tmp_path: Path) -> None:
    rec = tmp_path / "recording.h5"
    shutil.copy(tap_recording, rec)
    got: list[tuple[str, str]] = []
    report_build.solve_report(rec, lambda kind, msg, **kw: got.append((kind, msg)))
    assert got == [("info", f"report: {tmp_path / 'report.html'}")]
    assert {p.name for p in tmp_path.glob("*.png")} == {"sync_hist.png", "sync_residual.png"}


def test_without_matplotlib_the_command_says_what_to_install(tap_recording: Path, tmp_path: Path,
                                                            monkeypatch, capsys) -> None:
    from rigctl.cli import main

    with monkeypatch.context() as m:
        m.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
        assert main(["report", str(tap_recording), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "pip install 'rigctl[report]'" in err and "Traceback" not in err
    assert not (tmp_path / "report.html").exists()
    assert main(["report", str(tmp_path / "missing")]) == 2
    assert "no such run directory or recording" in capsys.readouterr().err
    bad = tmp_path / "bad.h5"
    with h5py.File(bad, "w") as f:
        f.attrs["format"] = "something-else"
    assert main(["report", str(bad)]) == 2
    assert "not a rigctl recording" in capsys.readouterr().err


def test_the_summary_shows_counts_whole(tmp_path: Path) -> None:
    """An imported 1 h bag's 360000 samples read "3.6e+05" in the summary (every number went
    through 5 significant digits): a count is shown whole."""
    n = 123_457
    rng = np.random.default_rng(3)
    rec = write_recording(tmp_path / "rec.h5", 100.0, angular_rate=rng.standard_normal((n, 3)) * 1e-3,
                          specific_force=rng.standard_normal((n, 3)) * 1e-2 + [0.0, 0.0, G0])
    out = report_build.build_report(rec, tmp_path / "rep")
    rows = {r[0]: r[1:] for r in Page(out.read_text()).rows["summary"] if r}
    assert rows["IMU samples"] == [str(n)], rows["IMU samples"]
    assert report_html.fmt(2.5) == "2.5" and report_html.fmt(1.234567) == "1.2346"
