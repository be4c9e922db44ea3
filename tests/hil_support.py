"""Helpers for the hardware-in-the-loop tests: emulated hardware + wired config + a run."""
from __future__ import annotations

import io
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import yaml

from rigctl.config import load_config
from rigctl.procedure import load_procedure
from rigctl.runner import run_procedure
from rigctl.sim.hardware import start_hardware
from rigctl.sim.wire_config import write_wire_config

ROOT = Path(__file__).resolve().parent.parent
SIM = ROOT / "configs" / "sim.yaml"


def sim_config(tmp: Path, **imu: Any):
    """configs/sim.yaml, with ``imu`` keys changed (e.g. rate_hz=2000)."""
    d = yaml.safe_load(SIM.read_text())
    d["imu"].update(imu)
    p = tmp / "physics.yaml"
    p.write_text(yaml.safe_dump(d))
    return load_config(p), d


@contextmanager
def hardware(tmp: Path, speed: float, **kw: Any):
    cfg, raw = sim_config(tmp)
    hw = start_hardware(cfg, speed, link_dir=tmp / "ports", **kw)
    try:
        yield hw, raw
    finally:
        hw.close()


def run(proc: str, cfg_path: Path, out: Path, params: dict[str, str]):
    cfg = load_config(cfg_path)
    p = load_procedure(ROOT / "procedures" / proc, params, cfg.limits)
    res = run_procedure(p, cfg, out, console=io.StringIO(), install_signals=False)
    assert res.exit_code == 0, res.message
    return res, cfg


def wired_run(tmp: Path, proc: str, params: dict[str, str], table: str, link: str, speed: float,
              during=None):
    """Run ``proc`` over the wire against fresh emulated hardware; returns (recording, truth, hw info)."""
    with hardware(tmp, speed) as (hw, raw):
        cfg_path = write_wire_config(tmp / "wired.yaml", raw, hw, table=table, link=link)
        timers = [threading.Timer(delay, fn) for delay, fn in (during or [])]
        for t in timers:
            t.start()
        t0 = time.perf_counter()
        try:
            res, cfg = run(proc, cfg_path, tmp / "runs", params)
        finally:
            for t in timers:
                t.cancel()
                t.join()
        info = {"wall_s": time.perf_counter() - t0, "truth": hw.truth(), "hw": hw,
                "imu_overflow": hw.slots["imu"].endpoint.overflow_bytes,
                "reconnects": {k: s.reconnects for k, s in hw.slots.items()}}
    return res.recording, cfg, info


def segments(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {k: f["segments"][k][()] for k in f["segments"]}


def window_means(path: Path, seg: dict[str, np.ndarray], kind: bytes, field: str) -> list[np.ndarray]:
    with h5py.File(path, "r") as f:
        data = f[f"imu/{field}"]
        return [data[int(a):int(z)].mean(axis=0) for k, a, z in
                zip(seg["kind"], seg["first_sample"], seg["last_sample"]) if k == kind]
