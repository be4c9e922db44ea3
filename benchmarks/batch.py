"""Batch analysis on Dask: wall time of `rigctl batch` over N emulated recordings with 1 and
2 local workers, in the same run (same recordings, same machine load). Recordings: short
24-position runs (warm-up 1 min, 2 s per orientation) of N emulated units.

Usage: python benchmarks/batch.py [N=8]. Last line: JSON with units in the keys.
"""
from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
RIGCTL = [str(Path(sys.executable).parent / "rigctl")]


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 8
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        base = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
        for i in range(n):
            base["seed"] = 100 + i
            base["imu"]["sim"]["accel_bias_mg"] = [1.0 + 0.5 * i, -1.5, 3.0]
            cfg = root / f"u{i}.yaml"
            cfg.write_text(yaml.safe_dump(base))
            subprocess.run([*RIGCTL, "run", "procedures/24pos.yaml", "--config", str(cfg), "-p", "warmup=1 min",
                            "-p", "sample=2 s", "--out", str(root / "runs")], cwd=ROOT, check=True,
                           capture_output=True)
        out = {"recordings": n}
        for w in (1, 2):
            t0 = time.perf_counter()
            subprocess.run([*RIGCTL, "batch", str(root / "runs" / "*" / "recording.h5"), "--workers", str(w),
                            "--spec", str(ROOT / "configs" / "spec-example.yaml"), "--db", str(root / f"w{w}.sqlite"),
                            "--out", str(root / f"s{w}")], cwd=ROOT, check=True, capture_output=True)
            dt = time.perf_counter() - t0
            out[f"wall_{w}_workers_s"] = round(dt, 2)
            print(f"{n} recordings, {w} worker(s): {dt:.1f} s ({dt / n:.2f} s per recording, incl. start-up)")
        out["speedup_2_over_1"] = round(out["wall_1_workers_s"] / out["wall_2_workers_s"], 2)
        print(json.dumps(out))


if __name__ == "__main__":
    main()
