"""Throughput and latency of the daemon's HTTP API and Unix socket (docs/daemon.md).

Starts `rigctl serve --http 127.0.0.1:0` on the built-in emulated rig (idle, or with
``--capture`` recording a warm-up in real time), then for each interface runs N clients that
send requests back to back for D seconds (HTTP: keep-alive, GET /api/status; socket: one
connection per request, status). Last line: one JSON object, units in the keys.

    .venv/bin/python benchmarks/daemon_http.py [--clients 50] [--seconds 10] [--capture]
"""
from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parent.parent


async def http_clients(port: int, token: str, n: int, seconds: float) -> list[float]:
    lat: list[float] = []
    end = time.monotonic() + seconds
    req = f"GET /api/status HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\r\n".encode()

    async def one() -> None:
        r, w = await asyncio.open_connection("127.0.0.1", port)
        while time.monotonic() < end:
            t0 = time.perf_counter()
            w.write(req)
            await w.drain()
            head = await r.readuntil(b"\r\n\r\n")
            await r.readexactly(int(re.search(rb"(?i)content-length: (\d+)", head).group(1)))
            lat.append(time.perf_counter() - t0)
        w.close()

    await asyncio.gather(*(one() for _ in range(n)))
    return lat


async def socket_clients(path: str, n: int, seconds: float) -> list[float]:
    lat: list[float] = []
    end = time.monotonic() + seconds
    msg = b'{"v": 1, "cmd": "status", "args": {}}\n'

    async def one() -> None:
        while time.monotonic() < end:
            t0 = time.perf_counter()
            r, w = await asyncio.open_unix_connection(path)
            w.write(msg)
            await w.drain()
            await r.read()
            w.close()
            lat.append(time.perf_counter() - t0)

    await asyncio.gather(*(one() for _ in range(n)))
    return lat


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clients", type=int, default=50)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--capture", action="store_true", help="record a warm-up in real time meanwhile")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="rigctl-bench-", dir="/tmp"))
    cfg = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    cfg.update(clock="real")
    (tmp / "cfg.yaml").write_text(yaml.safe_dump(cfg))
    exe = Path(sys.executable).parent / "rigctl"
    log = (tmp / "serve.log").open("w")
    p = subprocess.Popen([str(exe), "serve", "--config", str(tmp / "cfg.yaml"), "--runs", str(tmp / "runs"),
                          "--socket", str(tmp / "s" / "rigctl.sock"), "--http", "127.0.0.1:0"],
                         stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    try:
        end = time.monotonic() + 60
        while not (m := re.search(r"API at http://127\.0\.0\.1:(\d+)/", (tmp / "serve.log").read_text())):
            if time.monotonic() > end or p.poll() is not None:
                sys.exit("rigctl serve did not start:\n" + (tmp / "serve.log").read_text())
            time.sleep(0.1)
        port = int(m.group(1))
        token = (tmp / "runs" / ".rigctl-daemon" / "http-token").read_text().strip()
        sock = str(tmp / "s" / "rigctl.sock")
        if a.capture:
            sys.path.insert(0, str(ROOT))
            from rigctl.service import control
            control.wait_for_socket(Path(sock), 30)
            control.request(Path(sock), "submit", {"procedure": str(ROOT / "procedures" / "warmup.yaml"),
                                                   "params": {"warmup": f"{2 * a.seconds + 30:g} s"}})
            time.sleep(2)
        res: dict = {"clients": a.clients, "seconds": a.seconds, "capture": a.capture}
        for name, coro in (("http", http_clients(port, token, a.clients, a.seconds)),
                           ("socket", socket_clients(sock, a.clients, a.seconds))):
            lat = np.array(asyncio.run(coro))
            res[f"{name}_requests_per_s"] = round(len(lat) / a.seconds, 1)
            res[f"{name}_latency_p50_ms"] = round(1e3 * float(np.median(lat)), 2)
            res[f"{name}_latency_p99_ms"] = round(1e3 * float(np.percentile(lat, 99)), 2)
        print(json.dumps(res))
    finally:
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=30)
        log.close()


if __name__ == "__main__":
    main()
