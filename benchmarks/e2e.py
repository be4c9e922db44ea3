"""End-to-end: wall time of `rigctl run procedures/24pos.yaml` on the emulator (virtual time).

Prints the run's wall time, its simulated-time / wall-time ratio and the process CPU time (user +
sys) the run took, which a shared machine's load does not inflate the way it does the wall time.
Last line: one JSON object.
"""
from __future__ import annotations

import io
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from rigctl.config.config import load_config  # noqa: E402
from rigctl.engine.procedure import load_procedure  # noqa: E402
from rigctl.run.runner import run_procedure  # noqa: E402


def main() -> None:
    cfg = load_config(ROOT / "configs" / "sim.yaml")
    proc = load_procedure(ROOT / "procedures" / "24pos.yaml", limits=cfg.limits)
    with tempfile.TemporaryDirectory() as tmp:
        ru0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        res = run_procedure(proc, cfg, Path(tmp), console=io.StringIO(), install_signals=False)
        wall = time.perf_counter() - t0
        ru1 = resource.getrusage(resource.RUSAGE_SELF)
        cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
        import h5py

        with h5py.File(res.recording, "r") as f:
            sim_s = float(f["imu/time"][-1])
            n = f["imu/time"].shape[0]
    assert res.exit_code == 0, res.message
    print(f"24pos on the emulator: {sim_s:.0f} s of rig time, {n} IMU samples at {cfg.imu_rate_hz:g} Hz")
    print(f"wall time {wall:.2f} s (target <= 30 s), simulated/wall = {sim_s / wall:.0f}x, "
          f"CPU {cpu:.2f} s (user + sys, the run only: imports before it not counted)")
    print(json.dumps({"wall_s": round(wall, 3), "sim_time_s": round(sim_s, 1),
                      "sim_to_wall_ratio": round(sim_s / wall, 1), "run_cpu_s": round(cpu, 3)}))


if __name__ == "__main__":
    main()
