"""The lot summary of `rigctl batch` shows the units' own uncertainties beside the spread, and
names a parameter whose units' uncertainties differ by more than 10x: a lot of a 24-position
run (gyro scale from Earth rate alone, 1-sigma 2.2e5 ppm) and a full calibration (7.4 ppm)
printed 'gyro_scale_error_x ppm 2 -100000 140000 ...' with nothing to tell the mean is one
unit's undetermined value."""
from __future__ import annotations

import math

from rigctl.analysis import batch as B


def _summary() -> dict:
    def p(unit: str, vals: list[float], us: list[float]) -> dict:
        return {"unit": unit, "n": len(vals), "mean": sum(vals) / len(vals),
                "sd": math.sqrt(sum((v - sum(vals) / len(vals)) ** 2 for v in vals) / (len(vals) - 1)),
                "min": min(vals), "max": max(vals), "median_u": sorted(us)[len(us) // 2],
                "min_u": min(us), "max_u": max(us)}
    return {"runs": {"recordings": 2, "analysed": 2, "failed": [],
                     "verdicts": {"PASS": 0, "FAIL": 0, "INDETERMINATE": 0}, "no_verdict": [], "spec": False, "yield": None,
                     "parameters": {"accel_bias_x": p("mg", [2.088, 1.996], [0.069, 0.13]),
                                    "gyro_scale_error_x": p("ppm", [-190000.0, 1000.3], [220000.0, 7.4])}}}


def test_summary_shows_unit_uncertainties_and_names_the_uneven_parameter() -> None:
    text = B.summary_text(_summary())
    head = next(ln for ln in text.splitlines() if ln.strip().startswith("parameter"))
    assert head.split()[-4:] == ["u", "min", "u", "max"]
    row = next(ln for ln in text.splitlines() if ln.strip().startswith("gyro_scale_error_x"))
    assert row.split()[-2:] == ["7.4", "220000"]
    row = next(ln for ln in text.splitlines() if ln.strip().startswith("accel_bias_x"))
    assert row.split()[-2:] == ["0.069", "0.13"]
    warn = [ln for ln in text.splitlines() if "warning:" in ln]
    assert len(warn) == 1 and "(gyro_scale_error_x)" in warn[0] and "accel_bias_x" not in warn[0]


def test_summary_counts_and_names_analysed_runs_with_no_verdict() -> None:
    """The audit's batch: 4 recordings, 1 failed, 3 analysed: PASS, INDETERMINATE and a thermal
    run the spec measured nothing in. The old line said 'yield 50 % (PASS 1, FAIL 0,
    INDETERMINATE 1)' with nothing about the third analysed run."""
    def cal(overall: str | None) -> dict:
        payload = {"mode": "turntable", "results": {}}
        if overall is not None:
            payload["verdicts"] = {"overall": overall}
        return {"calibration": payload}
    recs = ["runs/L/a/recording.h5", "runs/L/b/recording.h5", "runs/L/thermal/recording.h5",
            "runs/L/broken/recording.h5"]
    results = [{"recording": recs[0], "ok": True, "results": cal("PASS"), "error": None},
               {"recording": recs[1], "ok": True, "results": cal("INDETERMINATE"), "error": None},
               {"recording": recs[2], "ok": True, "results": cal(None), "error": None},
               {"recording": recs[3], "ok": False, "results": {}, "error": "no data"}]
    summary = B.summarise(results, {r: "L" for r in recs})
    assert summary["L"]["no_verdict"] == [recs[2]]
    assert summary["L"]["yield"] == 0.5  # 1 PASS of the 2 with a verdict
    text = B.summary_text(summary)
    head = text.splitlines()[0]
    assert "3 analysed, 1 failed" in head and "yield 50 % of 2 with a verdict" in head, head
    assert "no verdict 1" in head, head
    named = [ln for ln in text.splitlines() if ln.strip().startswith("NO VERDICT")]
    assert len(named) == 1 and recs[2] in named[0], text


def test_a_spec_that_decided_nothing_is_not_called_no_spec() -> None:
    """With a spec and only recordings it measured nothing in, the yield is n/a for that reason
    (the line said 'n/a (no spec)'), and each is named; without a spec none is listed."""
    recs = ["runs/L/thermal1/recording.h5", "runs/L/thermal2/recording.h5"]
    results = [{"recording": r, "ok": True, "results": {"calibration": {"mode": "turntable", "results": {}}},
                "error": None} for r in recs]
    text = B.summary_text(B.summarise(results, {r: "L" for r in recs}, with_spec=True))
    assert "yield n/a (no recording with a verdict)" in text and "no verdict 2" in text, text
    assert sum(ln.strip().startswith("NO VERDICT") for ln in text.splitlines()) == 2, text
    text = B.summary_text(B.summarise(results, {r: "L" for r in recs}, with_spec=False))
    assert "yield n/a (no spec)" in text and "NO VERDICT" not in text and "no verdict" not in text, text
