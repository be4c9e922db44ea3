"""Test helpers: configs derived from the shipped ones, and the rigctl command."""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import h5py
import yaml

ROOT = Path(__file__).resolve().parent.parent

#: tolerance, s, for comparing a stored duration with the one asked for: the engine ends a window
#: at min(now, t_start + sample_s) and a resumed session adds its time offset to both ends, so
#: t_end - t_start is the asked duration only to the rounding of those sums (a few ulps of the
#: rig time: 4e-13 s at ~1e3 s, 1.5e-11 s at a day). 1 ns is far above that and far below any
#: real shortfall (a sample, a poll: >= 1 ms)
DURATION_EPS = 1e-9


#: configs/sim.yaml's slow noise terms (bias instability B, random walk K), zeroed: the tests
#: that check the declared error model against white-noise tolerances (segment means within
#: 5 sigma of the white noise, calibration coverage of the plain white-noise fit) run on white
#: noise only, as their premise says; the default config carries B and K (docs/emulator.md)
SLOW_NOISE_KEYS = ("gyro_bias_instability_deg_h", "gyro_rrw_deg_h_rth",
                   "accel_bias_instability_mg", "accel_rrw_m_s_h_rth")
WHITE_NOISE_ONLY = {f"imu__sim__{k}": 0.0 for k in SLOW_NOISE_KEYS}
#: derived_config changes: a power cycle draws no new turn-on bias (a test that sets the bias
#: step itself, tests/hil_support.power_loss, then knows it exactly)
NO_TURN_ON_DRAW = {"imu__sim__gyro_turn_on_repeatability_deg_h": 0.0, "imu__sim__accel_turn_on_repeatability_mg": 0.0}


def white_noise_only(truth_imu: dict) -> None:
    """The run's IMU (the emulator's ``/truth`` imu) has white noise only on both sensors: the
    premise of the tests that hold 5 s window means to 5 sigma of white noise, N sqrt(fs/n)
    (:data:`WHITE_NOISE_ONLY` and hil_support.white_sim zero the slow terms). Measured with the
    emulator at rest, 3820 windows of 500 samples at 100 Hz after its warm-up: on white noise
    only, the window means' spread about the declared model is 1.00-1.015 of N sqrt(fs/n) per
    axis (mean offset within 0.016 of it); on configs/sim.yaml (B and K on) 3.5-3.9 of it, with
    offsets of up to 4.7: a white-noise tolerance there would fail on most runs."""
    for sensor in ("accel_noise", "gyro_noise"):
        for axis in truth_imu[sensor]:
            slow = {k: axis[k]["value"] for k in ("Q", "B", "K", "R") if axis.get(k, {}).get("value")}
            if axis.get("gm"):
                slow["gm"] = axis["gm"]
            assert not slow, f"{sensor}: the tolerance counts white noise only, but the IMU also has {slow}"


#: rate random walk K from SI (u/s/sqrt(s)) to the unit calibrate's noise lines print, written
#: out here (not taken from rigctl): m/s/h/sqrt(h) and deg/h/sqrt(h)
K_FIELD = {"accel": 3600.0 * 60.0, "gyro": 180.0 / 3.141592653589793 * 3600.0 * 60.0}
_K_TEXT = re.compile(r"^  ([ag])([xyz]) +N .*, K (?:< ([0-9.e+-]+)|([0-9.e+-]+) \[([0-9.e+-]+), ([0-9.e+-]+)\])"
                     r" (?:m/s/h/sqrt\(h\)|deg/h/sqrt\(h\))")


def assert_k_lines_cover_truth(text: str, truth_imu: dict, blocks: int = 1) -> None:
    """Every noise-model line `rigctl calibrate` printed in ``text`` (``blocks`` calibrations of
    six channels) gives the rate random walk K as a 95 % upper bound or a 95 % interval, and that
    bound or interval holds the emulator's true K (``/truth`` imu, SI)."""
    lines = [ln for ln in text.splitlines() if re.match(r"^  [ag][xyz] +N ", ln)]  # ax ... gz
    assert len(lines) == 6 * blocks, lines
    for ln in lines:
        m = _K_TEXT.match(ln)
        assert m, f"K is neither a bound nor an interval: {ln}"
        sensor, axis = {"a": "accel", "g": "gyro"}[m.group(1)], "xyz".index(m.group(2))
        k = truth_imu[f"{sensor}_noise"][axis]["K"]["value"] * K_FIELD[sensor]
        if m.group(3) is not None:
            assert k < float(m.group(3)), (k, ln)
        else:
            assert float(m.group(5)) <= k <= float(m.group(6)), (k, ln)


def derived_config(tmp_path: Path, name: str = "sim.yaml", **changes: Any) -> Path:
    """A copy of configs/<name> with dotted-key changes, e.g. ``**{"clock": "scaled"}``."""
    data = yaml.safe_load((ROOT / "configs" / name).read_text())
    for dotted, value in changes.items():
        node = data
        keys = dotted.split("__")
        for k in keys[:-1]:
            node = node.setdefault(k, {})
        node[keys[-1]] = value
    out = tmp_path / f"derived-{name}"
    out.write_text(yaml.safe_dump(data))
    return out


def emulated_capture(tmp: Path, imu_sim: dict[str, Any], procedure: str, seed: int = 11) -> tuple[Path, dict]:
    """``rigctl run`` of ``procedure`` (YAML text) on configs/sim.yaml with ``imu.sim`` replaced:
    (the recording, its /truth's ``imu`` parameters). The run goes through
    :func:`rigctl_in_process` (its paths are absolute): the callers test the recording, not the
    process."""
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg["seed"] = seed
    cfg["imu"]["sim"] = imu_sim
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    (tmp / "procedure.yaml").write_text(procedure)
    r = rigctl_in_process("run", str(tmp / "procedure.yaml"), "--config", str(tmp / "cfg.yaml"), "--out",
                          str(tmp / "runs"))
    assert r.returncode == 0, r.stderr[-2000:]
    (rec,) = sorted((tmp / "runs").glob("*/recording.h5"))
    with h5py.File(rec, "r") as f:
        truth = json.loads(f["truth"].attrs["params_json"])["imu"]
    return rec, truth


def copy_recording(rec: Path, dest: Path) -> Path:
    """A copy of a shared session fixture's recording (e.g. conftest's declared_only_hour) in
    ``dest``: what one file's commands write into it (/results) stays out of the others' view."""
    import shutil

    dest.mkdir(parents=True, exist_ok=True)
    return Path(shutil.copy2(rec, dest / rec.name))


def rigctl_cmd() -> list[str]:
    exe = Path(sys.executable).parent / "rigctl"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "rigctl.cli"]


def run_rigctl(*args: str, timeout: float = 120, **kw: Any) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run([*rigctl_cmd(), *args], capture_output=True, text=True, timeout=timeout,
                          cwd=kw.pop("cwd", ROOT), env=env, **kw)


def rigctl_in_process(*args: str) -> subprocess.CompletedProcess:
    """``rigctl ARGS`` through :func:`rigctl.cli.main` in this process, stdout and stderr captured:
    what :func:`run_rigctl` returns, without a new interpreter and its imports (~4 s of CPU of a
    ``rigctl calibrate`` subprocess's 6.4 s, against ~2.5 s for the same calibration in process).
    For what a command computes and writes; a test about the process (exit status as the shell
    sees it, the console, signals) runs the real command."""
    import contextlib
    import io

    from rigctl import cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main(list(args))
    return subprocess.CompletedProcess(["rigctl", *args], code, out.getvalue(), err.getvalue())


#: a short procedure for the full-disk tests (in-process and over the wire)
DISK_PROCEDURE = """procedure: disk
steps:
  - warmup:
      duration: 10 s
  - orientations:
      angles_deg: [[0, 0, 0], [90, 0, 0], [0, 90, 0]]
      sample: 5 s
      settle: {hold: 1 s, timeout: 60 s}
"""


def fill_disk(path: Path | str) -> None:
    """Write zeros to ``path`` until its filesystem is full (unbuffered: a buffered file's close
    would try to write its last partial buffer again and raise ENOSPC out of the helper)."""
    try:
        with open(path, "wb", buffering=0) as fh:
            while True:
                fh.write(b"\0" * 65536)
    except OSError:
        pass


def make_cut_off(run_dir: Path, recording: Path) -> None:
    """Make a complete two-step run look cut off during its second step, as a kill leaves it:
    checkpoint after step 1 (status running), file status running, one complete segment."""
    import json

    import h5py

    ck = json.loads((run_dir / "checkpoint.json").read_text())
    ck.update(status="running", last_step=0)
    (run_dir / "checkpoint.json").write_text(json.dumps(ck))
    with h5py.File(recording, "r+") as f:
        f["run/status"][0] = b"running"
        for k in f["segments"]:
            f["segments"][k].resize(1, axis=0)


def start_process(cmd: list[str], log: Path, ready: str, timeout: float = 60.0,
                  cwd: Path = ROOT) -> tuple[subprocess.Popen, str]:
    """Start ``cmd`` (stdout and stderr to ``log``, a session of its own) and wait until its
    output matches the regex ``ready``: (the process, its output so far)."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    out = log.open("w")
    p = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        text = log.read_text()
        if re.search(ready, text):
            return p, text
        if p.poll() is not None:
            break
        time.sleep(0.05)
    p.kill()
    raise AssertionError(f"{cmd[:3]} did not get ready:\n{log.read_text()[-3000:]}")


def stop_process(p: subprocess.Popen) -> None:
    """SIGTERM, then after 20 s SIGKILL, a process of :func:`start_process` still running."""
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(timeout=20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


#: warm-up, a 2-minute capture, then the Allan analysis and the report (allan-overnight's
#: solvers): a run whose analysis lasts seconds, for the tests that interrupt it
SHORT_ALLAN_PROCEDURE = """procedure: short-allan
steps:
  - warmup:
      duration: 2 s
  - capture:
      duration: 2 min
      label: static
  - solve:
      solvers: [allan, report]
"""


def allan_whole_or_absent(rec: Path) -> bool:
    """True when /results/allan is there and whole (its JSON parses, every axis it names has
    its curve datasets), False when absent; an assertion error when half-written."""
    with h5py.File(rec, "r") as f:
        if "results" not in f or "allan" not in f["results"]:
            return False
        g = f["results/allan"]
        summary = json.loads(g.attrs["json"])
        assert summary["axes"], summary
        for axis in summary["axes"]:
            assert {"tau_s", "m", "edf"} <= set(g[axis]), (axis, list(g[axis]))
        return True
