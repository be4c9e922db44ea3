"""`rigctl calibrate --spec` on an emulated full calibration, and its certificate as a PDF,
checked as a person would: pdftotext for the text, pdftoppm for a PNG that is not blank (and
that was looked at while writing this test)."""
from __future__ import annotations

import re
import shutil
import subprocess

import numpy as np
import pytest

from helpers import run_rigctl


def test_calibrate_spec_and_certificate(full_calibration_run, tmp_path):
    run_dir, _ = full_calibration_run
    rec = run_dir / "recording.h5"
    r = run_rigctl("calibrate", str(rec), "--spec", "configs/spec-example.yaml", "--db", str(tmp_path / "r.sqlite"))
    assert r.returncode == 0, r.stderr[-1500:]
    table = r.stdout.split("Verdicts against")[1]
    rows = re.findall(r"^\s+(\w+)\s+(\S+)\s+\S+\s+\S+\s+\[.*?\]\s+.*?(PASS|FAIL|INDETERMINATE)\s*$", table, re.M)
    names = {n: (unit, v) for n, unit, v in rows}
    for ax in "xyz":  # configs/sim.yaml: biases 2, -1.5, 3 mg and 20, -15, 10 deg/h: well inside
        assert names[f"accel_bias_{ax}"] == ("mg", "PASS")
        assert names[f"gyro_bias_{ax}"] == ("deg/h", "PASS")
        assert names[f"gyro_scale_error_{ax}"][0] == "ppm"
    overall = re.search(r"^OVERALL: (\S+)", r.stdout, re.M).group(1)
    assert overall == ("FAIL" if any(v == "FAIL" for _, v in names.values()) else
                       "INDETERMINATE" if any(v == "INDETERMINATE" for _, v in names.values()) else "PASS")
    assert "not measured here: gyro_angle_random_walk_[xyz]" in r.stdout
    if shutil.which("pdftoppm") is None or shutil.which("chromium") is None:
        pytest.fail("pdftoppm (poppler-utils) and chromium are needed: .ci/run installs them")
    r = run_rigctl("certificate", str(run_dir), "--spec", "configs/spec-example.yaml", "--out", str(tmp_path / "c"))
    assert r.returncode == 0, r.stderr[-1500:]
    pdf = tmp_path / "c" / "certificate.pdf"
    text = subprocess.run(["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True, timeout=60).stdout
    flat = " ".join(text.split())
    for needle in ("Calibration certificate", "Unit under test", "EMU-declared-", "full-calibration",
                   "rigctl emulator (no physical traceability)", "IMU temperature", "degC",
                   "accel_bias_x", "U (95 %)", "guarded acceptance", "JCGM 106", "Signatures", "checked by",
                   "Specified but not measured", "No Allan analysis of this unit",
                   # the certificate decides everything the spec asks: the noise terms are not
                   # measured (no Allan capture of this unit), so at best INDETERMINATE
                   "Overall verdict against MEMS IMU acceptance (example): "
                   + ("FAIL" if overall == "FAIL" else "INDETERMINATE")):
        assert needle in flat, needle
    m = re.search(r"accel_bias_y\s+mg\s+(\S+)\s+(\S+)\s+1\.96", text)
    assert m and abs(float(m.group(1)) + 1.5) < 3 * float(m.group(2))  # -1.5 mg within its U
    subprocess.run(["pdftoppm", "-r", "50", "-png", "-f", "1", "-l", "1", str(pdf), str(tmp_path / "p")],
                   check=True, timeout=60)
    png = next(tmp_path.glob("p*.png"))
    import matplotlib.image as mpimg

    px = mpimg.imread(png)[..., :3]
    assert px.shape[0] > px.shape[1] > 300          # a portrait A4 page
    dark = np.mean(px < 0.5)
    assert 0.01 < dark < 0.3                          # text on white: neither blank nor black
    colour = np.mean((np.abs(px[..., 0] - px[..., 1]) > 0.2) | (np.abs(px[..., 1] - px[..., 2]) > 0.2))
    assert colour > 1e-4                              # the coloured verdicts are drawn
