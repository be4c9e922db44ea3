"""report.html of an emulated full calibration, rendered in headless Chromium (issue 9)."""
import html.parser
import shutil
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

from helpers import run_rigctl

pytest.importorskip("matplotlib")

SECTION_IDS = ("summary", "table", "calibration", "closed-loop", "allan", "sync", "events", "provenance")


class _Collect(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.ids, self.imgs, self.external = set(), {}, []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.add(a["id"])
        if tag == "img":
            self.imgs[a.get("id", "")] = a.get("src", "")
        for key in ("src", "href"):
            v = a.get(key, "")
            if v and not v.startswith(("data:", "#")):
                self.external.append(v)


def _png_pixels(path: Path) -> np.ndarray:
    import matplotlib.image as mpimg

    return mpimg.imread(path)


@pytest.fixture
def calibrated_run(full_calibration_run):
    return full_calibration_run


def test_full_calibration_writes_a_self_contained_report(calibrated_run):
    run_dir, stdout = calibrated_run
    report = run_dir / "report.html"
    assert report.is_file(), stdout[-2000:]
    p = _Collect()
    p.feed(report.read_text())
    from rigctl.report.report_html import SECTIONS

    for sid, _title in SECTIONS:
        assert sid in p.ids, f"section {sid} missing"
    assert not p.external, f"external resources: {p.external[:3]}"
    for pid in ("plot-table_timeline", "plot-cal_residuals_orientation", "plot-cal_residuals_rate",
                "plot-cal_rms"):
        assert pid in p.imgs and p.imgs[pid].startswith("data:image/png;base64,"), pid
        assert len(p.imgs[pid]) > 5000
    text = report.read_text()
    assert "RMS before" in text or "before" in text  # closed loop's before/after table


def test_report_renders_in_headless_chromium(calibrated_run, tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("Debian's chromium is not installed (.ci/run installs it)")
    run_dir, _ = calibrated_run
    shot = tmp_path / "shot.png"
    cmd = [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'profile'}", f"--screenshot={shot}", "--window-size=1280,3000",
           (run_dir / "report.html").as_uri()]
    subprocess.run(cmd, capture_output=True, timeout=120)
    assert shot.is_file() and shot.stat().st_size > 20000
    px = _png_pixels(shot)
    rgb = (px[..., :3] * 255).astype(np.uint8).reshape(-1, 3)
    colours = np.unique(rgb[:: 7], axis=0)
    assert len(colours) > 200, "screenshot looks blank"
    assert np.mean(np.all(rgb > 245, axis=1)) < 0.97  # not all white
    assert zlib.crc32(shot.read_bytes()) != 0


def test_report_command_on_a_run_dir_and_bad_input(calibrated_run, tmp_path):
    run_dir, _ = calibrated_run
    r = run_rigctl("report", str(run_dir), "--out", str(tmp_path / "rep"))
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "rep" / "report.html").is_file()
    r = run_rigctl("report", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and "Traceback" not in r.stderr
