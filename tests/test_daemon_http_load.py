"""Load on a real `rigctl serve --http` process while it records an emulated capture over the
wire (`rigctl sim up` in its own process: Xsens IMU and ACL table on ptys, real time):
100 HTTP clients (90 polling the API, 10 holding the live event stream) and 100 Unix-socket
clients for 30 s, plus a silent client on each interface and a 10 MB request. The daemon must
answer every request, the recording must have every IMU sample the emulator sent (no counter
gap, no suspension), and the silent clients must not hold anyone up."""
from __future__ import annotations

import asyncio
import json
import re
import shutil
import socket
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml

pytest.importorskip("starlette")

from rigctl.service import control  # noqa: E402

from helpers import ROOT, rigctl_cmd, start_process, stop_process  # noqa: E402

LOAD_S = 30.0
N_HTTP, N_STREAMS, N_SOCK = 90, 10, 100
THINK_S = 0.2          # each polling client waits this long between requests
IMU_HZ = 200
CAPTURE_S = 36         # rig seconds (real time): the load runs inside it


async def _http_get(reader, writer, path: str, token: str) -> tuple[int, bytes]:
    writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {token}\r\n\r\n".encode())
    await writer.drain()
    head = await reader.readuntil(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    length = int(re.search(rb"(?i)content-length: (\d+)", head).group(1))
    return status, await reader.readexactly(length)


async def _load(port: int, token: str, sock: Path, stats: dict) -> None:
    end = time.monotonic() + LOAD_S
    paths = ["/api/status", "/api/queue", "/api/live?since=0", "/api/history", "/api/runs"]

    async def http_client(n: int) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        k = n
        while time.monotonic() < end:
            t0 = time.monotonic()
            try:
                status, body = await asyncio.wait_for(_http_get(reader, writer, paths[k % len(paths)], token), 20)
                ok = status == 200 and json.loads(body)["ok"] is True
            except (OSError, asyncio.IncompleteReadError, asyncio.TimeoutError, ValueError) as exc:
                ok = False
                stats["errors"].append(f"http {n}: {type(exc).__name__}: {exc}")
                writer.close()
                reader, writer = await asyncio.open_connection("127.0.0.1", port)
            stats["http_ok" if ok else "http_bad"] += 1
            stats["http_max_s"] = max(stats["http_max_s"], time.monotonic() - t0)
            k += 1
            await asyncio.sleep(THINK_S)
        writer.close()

    async def stream_client(n: int) -> None:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(f"GET /api/events HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n\r\n".encode())
        await writer.drain()
        head = await reader.readuntil(b"\r\n\r\n")
        assert b" 200 " in head.split(b"\r\n")[0], head
        while time.monotonic() < end:
            line = await asyncio.wait_for(reader.readline(), 20)
            if line.startswith(b"event: live"):
                stats["stream_events"] += 1
        writer.close()

    async def sock_client(n: int) -> None:
        msg = json.dumps({"v": 1, "cmd": "status" if n % 2 else "queue", "args": {}}).encode() + b"\n"
        while time.monotonic() < end:
            t0 = time.monotonic()
            try:
                reader, writer = await asyncio.open_unix_connection(str(sock))
                writer.write(msg)
                await writer.drain()
                data = await asyncio.wait_for(reader.read(), 20)
                writer.close()
                ok = json.loads(data)["ok"] is True
            except (OSError, asyncio.TimeoutError, ValueError) as exc:
                ok = False
                stats["errors"].append(f"sock {n}: {type(exc).__name__}: {exc}")
            stats["sock_ok" if ok else "sock_bad"] += 1
            stats["sock_max_s"] = max(stats["sock_max_s"], time.monotonic() - t0)
            await asyncio.sleep(THINK_S)

    async def oversized() -> None:
        await asyncio.sleep(LOAD_S / 2)
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(f"POST /api/queue HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                     f"Content-Type: application/json\r\nContent-Length: {10 * 1024 * 1024}\r\n\r\n".encode())
        writer.write(b"{" + b" " * 65536)
        await writer.drain()
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 20)
        stats["oversized"] = head.split(b"\r\n")[0].decode()
        writer.close()

    await asyncio.gather(*(http_client(n) for n in range(N_HTTP)), *(stream_client(n) for n in range(N_STREAMS)),
                         *(sock_client(n) for n in range(N_SOCK)), oversized())


def test_200_clients_for_30s_while_capturing_lose_no_sample(tmp_path):
    base = Path(tempfile.mkdtemp(prefix="rigctl-load-", dir="/tmp"))  # short AF_UNIX paths
    physics = yaml.safe_load((ROOT / "configs" / "sim.yaml").read_text())
    physics["imu"]["rate_hz"] = IMU_HZ
    (tmp_path / "physics.yaml").write_text(yaml.safe_dump(physics))
    wired, sock, runs = tmp_path / "wired.yaml", base / "ctl" / "rigctl.sock", tmp_path / "runs"
    sim = serve = None
    silent_tcp = silent_unix = None
    try:
        sim, _ = start_process([*rigctl_cmd(), "sim", "up", "--config", str(tmp_path / "physics.yaml"), "--speed", "1",
                         "--wire-config", str(wired), "--link-dir", str(base / "ports")],
                        tmp_path / "sim.log", r"(?m)^ready$")
        serve, text = start_process([*rigctl_cmd(), "serve", "--config", str(wired), "--runs", str(runs),
                              "--socket", str(sock), "--http", "127.0.0.1:0"],
                             tmp_path / "serve.log", r"API at http://127\.0\.0\.1:\d+/")
        port = int(re.search(r"API at http://127\.0\.0\.1:(\d+)/", text).group(1))
        assert control.wait_for_socket(sock, 30)
        token = (runs / ".rigctl-daemon" / "http-token").read_text().strip()
        reply = control.request(sock, "submit", {"procedure": str(ROOT / "procedures" / "warmup.yaml"),
                                                 "params": {"warmup": f"{CAPTURE_S} s"}})
        assert reply["ok"], reply
        end = time.monotonic() + 60
        while not (st := control.request(sock, "status")).get("imu_samples"):
            assert time.monotonic() < end, st
            time.sleep(0.1)

        # a client on each interface that connects and sends nothing, for the whole load
        silent_tcp = socket.create_connection(("127.0.0.1", port))
        silent_unix = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        silent_unix.connect(str(sock))
        stats = {"http_ok": 0, "http_bad": 0, "sock_ok": 0, "sock_bad": 0, "http_max_s": 0.0, "sock_max_s": 0.0,
                 "stream_events": 0, "errors": [], "oversized": None}
        t0 = time.monotonic()
        asyncio.run(_load(port, token, sock, stats))
        wall = time.monotonic() - t0
        during = control.request(sock, "status")
        assert during["state"] == "running" and during["job"]["id"] == reply["job"], during  # the load ran inside the capture
        print(json.dumps({k: v for k, v in stats.items() if k != "errors"}), f"wall {wall:.1f} s")
        assert not stats["errors"], stats["errors"][:5]
        assert stats["http_bad"] == 0 and stats["sock_bad"] == 0
        # every client was served all along: at least half the requests its think time allows
        assert stats["http_ok"] > 0.5 * N_HTTP * LOAD_S / THINK_S / 2, stats
        assert stats["sock_ok"] > 0.5 * N_SOCK * LOAD_S / THINK_S / 2, stats
        assert stats["stream_events"] >= N_STREAMS * LOAD_S / 0.5 * 0.5, stats  # live batches every 0.5 s
        assert stats["oversized"].startswith("HTTP/1.1 413"), stats["oversized"]

        # the job finishes; the recording holds every sample the IMU sent
        end = time.monotonic() + CAPTURE_S + 30
        while (job := control.request(sock, "queue")["jobs"][-1])["state"] in ("queued", "running"):
            assert time.monotonic() < end, job
            time.sleep(0.2)
        assert job["state"] == "complete", job
        with h5py.File(Path(job["run_dir"]) / "recording.h5", "r") as f:
            counter = f["imu/counter"][()].astype(np.int64)
            kinds = [k.decode() for k in f["events/kind"][()]]
            msgs = [m.decode() for m in f["events/message"][()]]
            status = f["run/status"][0].decode()
        assert status == "complete"
        steps = np.diff(counter)
        assert len(counter) >= CAPTURE_S * IMU_HZ * 0.95, len(counter)
        assert (steps == 1).all(), f"{int((steps != 1).sum())} counter gaps, {int(steps[steps > 1].sum() - (steps > 1).sum())} samples lost"
        assert not any(k in ("suspend", "incomplete", "data-lost") for k in kinds), list(zip(kinds, msgs))
        assert not any("imu-gap" in m or "imu-link" in m for m in msgs), msgs
    finally:
        for s in (silent_tcp, silent_unix):
            if s is not None:
                s.close()
        for p in (serve, sim):
            if p is not None:
                stop_process(p)
        shutil.rmtree(base, ignore_errors=True)
