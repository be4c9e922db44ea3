"""The daemon's web page in headless Chromium (driven through the DevTools protocol with real
mouse and keyboard input) against a daemon running an emulated capture: a control without the
token is refused, the live IMU plot and values move, the queue is edited from the page, and a
screenshot is taken."""
from __future__ import annotations

import io
import json
import re
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("websockets")

from rigctl.service.daemon import Daemon  # noqa: E402
from rigctl.run.runner import RunOptions  # noqa: E402
from rigctl.config.suspenders import SuspenderSettings  # noqa: E402

from cdp import Browser, chromium_path  # noqa: E402
from helpers import ROOT, derived_config  # noqa: E402
from test_daemon_http import Client  # noqa: E402

G0 = 9.80665


@pytest.fixture
def capturing(tmp_path):
    """A daemon on the emulated rig (20x real time) with a long warm-up capture running."""
    cfg = derived_config(tmp_path, clock="scaled", speed=20.0)
    base = Path(tempfile.mkdtemp(prefix="rigctl-web-", dir="/tmp"))
    d = Daemon(tmp_path / "runs", cfg, base / "ctl" / "rigctl.sock", console=io.StringIO(),
               options=RunOptions(suspenders=SuspenderSettings(hold_s=0.5, min_free_bytes=0)))
    d.start()
    web = d.start_http("127.0.0.1", 0, procedures_dir=ROOT / "procedures")
    token = (d.runs_dir / ".rigctl-daemon" / "http-token").read_text().strip()
    api = Client(web.url, token)
    st, r = api("POST", "/api/queue", {"procedure": "warmup.yaml", "params": {"warmup": "20 min"}})
    assert st == 200, r
    end = time.monotonic() + 20
    while api("GET", "/api/status")[1]["state"] != "running":
        assert time.monotonic() < end, "the capture did not start"
        time.sleep(0.05)
    try:
        yield d, web, api, r["job"]
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)


def test_page_shows_live_imu_refuses_control_without_token_and_edits_the_queue(capturing, tmp_path):
    if chromium_path() is None:
        pytest.fail("Debian's chromium is needed: .ci/run installs it")
    d, web, api, capture_job = capturing
    b = Browser(tmp_path / "profile")
    try:
        # 1) without the token: nothing live, and a control is refused by the daemon
        b.goto(web.url)
        b.wait_for("document.getElementById('conn').textContent.includes('token needed')", 10, "token notice")
        b.click("#btn-pause")
        b.wait_for("document.body.dataset.lastControl === '401'", 10, "the refused pause")
        assert "refused (401)" in b.js("document.getElementById('message').textContent")
        st = api("GET", "/api/status")[1]
        assert st["state"] == "running" and "operator" not in (st.get("suspenders") or {}), st
        assert b.js("document.body.dataset.liveReceived") is None

        # 2) the operator pastes the token: the live view starts and moves
        b.type("#token", api.token)
        b.click("#token-form button")
        b.wait_for("Number(document.body.dataset.liveReceived) > 20", 15, "live IMU points")
        # the newest point's time and the text showing it, read in one evaluation: the page sets
        # both in one call per live batch (a batch every 0.5 s, ~10 s of rig time at 20x), so two
        # reads could straddle a batch and the wait below return before the next one
        t1, text1 = b.js("[Number(document.body.dataset.liveLastT), "
                         "document.getElementById('live-values').textContent]")
        b.wait_for(f"Number(document.body.dataset.liveLastT) > {t1 + 5}", 15, "newer live points")
        text2 = b.js("document.getElementById('live-values').textContent")
        assert text1 != text2
        # the newest point the page shows: a resting IMU reads 1 g (field units on the page)
        f = [float(v) for v in re.search(r"f \[([^\]]+)\] g", text2).group(1).split(",")]
        assert abs(np.linalg.norm(f) - 1.0) < 0.01, text2
        w = [float(v) for v in re.search(r"w \[([^\]]+)\] deg/s", text2).group(1).split(",")]
        assert np.linalg.norm(w) < 0.5, text2  # at rest: Earth rate plus noise and bias, well under 0.5 deg/s
        # the plot has ink: pixels that are not background in the specific-force canvas
        ink = b.js("""(() => { const c = document.getElementById('plot-accel');
            const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; let n = 0;
            for (let i = 0; i < d.length; i += 4) if (d[i + 3] > 0 && (d[i] < 200 || d[i + 1] < 200 || d[i + 2] < 200)) n++;
            return n; })()""")
        assert ink > 1500, ink
        assert b.js("document.getElementById('state').textContent") == "running"

        # 3) the queue, edited from the page (the capture keeps running)
        b.js("document.getElementById('add-proc').value = 'warmup.yaml'")
        b.type("#add-params", "warmup=7 s")
        b.click("#btn-add")
        b.wait_for("document.body.dataset.lastControl === '200'", 10, "the first add")
        q = api("GET", "/api/queue")[1]
        assert len(q["queued"]) == 1
        first = q["queued"][0]
        assert next(j for j in q["jobs"] if j["id"] == first)["params"] == {"warmup": "7 s"}
        b.js("document.body.dataset.lastControl = ''")
        b.type("#add-params", "warmup=8 s")
        b.type("#add-pos", "1")
        b.click("#btn-add")
        b.wait_for("document.body.dataset.lastControl === '200'", 10, "the second add")
        q = api("GET", "/api/queue")[1]
        assert len(q["queued"]) == 2 and q["queued"][1] == first
        second = q["queued"][0]
        b.wait_for(f"document.body.dataset.queued === '{second},{first}'", 10, "the queue table")
        b.click(f"#queue tr[data-job='{first}'] button:nth-of-type(1)")  # up
        b.wait_for(f"document.body.dataset.queued === '{first},{second}'", 10, "the moved row")
        assert api("GET", "/api/queue")[1]["queued"] == [first, second]
        b.click(f"#queue tr[data-job='{second}'] button.danger")  # remove
        b.wait_for(f"document.body.dataset.queued === '{first}'", 10, "the removed row")
        assert api("GET", "/api/queue")[1]["queued"] == [first]
        b.click("#btn-qstop")
        b.wait_for("document.getElementById('st-queue').textContent.includes('stopped')", 10, "queue stopped")
        assert api("GET", "/api/status")[1]["queue_running"] is False

        shot = b.screenshot(tmp_path / "daemon-page.png")
        import matplotlib.image as mpimg
        px = (mpimg.imread(shot)[..., :3] * 255).astype(np.uint8).reshape(-1, 3)
        assert len(np.unique(px[::5], axis=0)) > 100, "screenshot looks blank"

        # 4) abort from the page, with the token: the capture ends interrupted, the queue stays stopped
        b.click("#btn-abort")
        end = time.monotonic() + 20
        while (job := next(j for j in api("GET", "/api/queue")[1]["jobs"] if j["id"] == capture_job))["state"] == "running":
            assert time.monotonic() < end, job
            time.sleep(0.1)
        assert job["state"] == "interrupted" and "abort" in job["message"]
        assert api("GET", "/api/queue")[1]["queued"] == [first]
        errors = [c for c in b.console if c.startswith("exception")]
        assert not errors, errors
    finally:
        b.close()
