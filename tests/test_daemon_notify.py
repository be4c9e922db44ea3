"""The daemon's notices (rigctl/config/notify.py) against a local HTTP receiver (http.server) and a
local SMTP server (aiosmtpd) started here: a job complete, a job failed (settle timeout), a
pause longer than the set time, and a device fault that leaves the rig faulted."""
from __future__ import annotations

import io
import json
import shutil
import socket
import tempfile
import threading
import time
from contextlib import contextmanager
from email import message_from_bytes, policy
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest
import yaml

from rigctl.service import control
from rigctl.config.config import load_config
from rigctl.service.daemon import Daemon
from rigctl.devices import DeviceFault
from rigctl.engine.rig import open_rig
from rigctl.run.runner import RunOptions
from rigctl.config.suspenders import SuspenderSettings
from rigctl.yamlio import InputError

from helpers import ROOT, derived_config

aiosmtpd_controller = pytest.importorskip("aiosmtpd.controller")


class Receiver(BaseHTTPRequestHandler):
    got: list[dict] = []

    def do_POST(self):  # noqa: N802 - http.server's name
        body = self.rfile.read(int(self.headers["Content-Length"]))
        type(self).got.append({"type": self.headers["Content-Type"], **json.loads(body)})
        self.send_response(204)
        self.end_headers()

    def log_message(self, *args):
        pass


class Mailbox:
    def __init__(self):
        self.mails: list = []

    async def handle_DATA(self, server, session, envelope):  # noqa: N802 - aiosmtpd's name
        self.mails.append((envelope.mail_from, list(envelope.rcpt_tos), message_from_bytes(envelope.content, policy=policy.default)))
        return "250 OK"


def bound_socket() -> socket.socket:
    """A TCP socket bound to a loopback port the kernel chose, held for the caller: a port
    looked up, closed and bound again later can be taken meanwhile by any other process
    (another xdist worker's server or client) -- the port stays ours while this socket lives."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.bind(("127.0.0.1", 0))
    return s


class SmtpOnSocket(aiosmtpd_controller.Controller):
    """aiosmtpd's threaded Controller serving on a socket bound beforehand (``bound_socket``)
    instead of binding its host:port itself after we looked a free one up."""

    def __init__(self, handler, sock: socket.socket, **kw) -> None:
        host, port = sock.getsockname()[:2]
        super().__init__(handler, hostname=host, port=port, **kw)
        self._sock = sock

    def _create_server(self):
        return self.loop.create_server(self._factory_invoker, sock=self._sock, ssl=self.ssl_context)


@pytest.fixture
def receivers():
    Receiver.got = []
    http = ThreadingHTTPServer(("127.0.0.1", 0), Receiver)
    threading.Thread(target=http.serve_forever, daemon=True).start()
    box = Mailbox()
    # ready_timeout: aiosmtpd's default 5 s for its thread to start serving is a wall-clock
    # deadline on a loaded machine; the test's own waits are 20-30 s
    smtp = SmtpOnSocket(box, bound_socket(), ready_timeout=60.0)
    smtp.start()
    try:
        yield http.server_address[1], smtp.port, box
    finally:
        smtp.stop()
        http.shutdown()


def wait_for(pred, timeout, what):
    end = time.monotonic() + timeout
    while not (v := pred()):
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.05)
    return v


def test_notices_by_webhook_and_email(receivers, tmp_path):
    http_port, smtp_port, box = receivers
    cfg = derived_config(tmp_path, clock="scaled", speed=20.0, notifications={
        "events": ["complete", "failed", "suspended", "faulted"], "suspended_after_s": "1 s",
        "webhook": {"url": f"http://127.0.0.1:{http_port}/rig-hook", "timeout_s": 5},
        "email": {"smtp_host": "127.0.0.1", "smtp_port": smtp_port, "from": "rig@lab.example",
                  "to": ["night@lab.example", "boss@lab.example"]}})
    fault = {"on": False}

    @contextmanager
    def opener(c):
        with open_rig(c) as (rig, truth):
            if fault["on"]:  # another unit answers on the IMU port after a few reads
                read, n = rig.imu.read, [0]

                def faulty():
                    n[0] += 1
                    if n[0] > 20:
                        raise DeviceFault("another unit answers on the IMU port")
                    return read()
                rig.imu.read = faulty
            yield rig, truth

    base = Path(tempfile.mkdtemp(prefix="rigctl-notify-", dir="/tmp"))
    sock = base / "ctl" / "rigctl.sock"
    console = io.StringIO()
    d = Daemon(tmp_path / "runs", cfg, sock, console=console,
               options=RunOptions(suspenders=SuspenderSettings(hold_s=0.5, min_free_bytes=0), rig_opener=opener))
    d.start()
    warm = str(ROOT / "procedures" / "warmup.yaml")
    try:
        def notices(event):
            return [n for n in Receiver.got if n["event"] == event]

        def mails(word):
            return [m for m in box.mails if word in m[2]["Subject"]]

        # 1) complete
        assert control.request(sock, "submit", {"procedure": warm, "params": {"warmup": "10 s"}})["ok"]
        hook = wait_for(lambda: notices("complete"), 30, "the 'complete' webhook")[0]
        assert hook["type"] == "application/json" and hook["job"]["id"] == 1 and hook["job"]["state"] == "complete"
        assert hook["rig"] == load_config(cfg).name and hook["job"]["params"] == {"warmup": "10 s"}
        sender, rcpt, mail = wait_for(lambda: mails("job 1 complete"), 30, "the 'complete' e-mail")[0]
        assert sender == "rig@lab.example" and rcpt == ["night@lab.example", "boss@lab.example"]
        assert "warmup.yaml" in mail["Subject"] and "event:    complete" in mail.get_content()

        # 2) a pause longer than suspended_after_s (1 s): one notice naming the reason; abort
        #    ('interrupted' is not among the configured events: no notice)
        assert control.request(sock, "submit", {"procedure": warm, "params": {"warmup": "20 min"}})["ok"]
        wait_for(lambda: control.request(sock, "status")["state"] == "running", 20, "running")
        assert control.request(sock, "pause")["ok"]
        t0 = time.monotonic()
        hook = wait_for(lambda: notices("suspended"), 20, "the 'suspended' webhook")[0]
        assert time.monotonic() - t0 >= 0.9
        assert "operator: paused by operator" in hook["message"] and hook["job"]["id"] == 2
        wait_for(lambda: mails("job 2 suspended"), 20, "the 'suspended' e-mail")
        time.sleep(1.5)
        assert len(notices("suspended")) == 1  # once per pause
        assert control.request(sock, "abort")["ok"]
        wait_for(lambda: control.request(sock, "queue")["jobs"][-1]["state"] == "interrupted", 20, "abort")
        assert control.request(sock, "status")["queue_running"] is False  # an abort stops the queue
        assert control.request(sock, "queue_start")["ok"]

        # 3) failed: a settle timeout
        bad = tmp_path / "unsettled.yaml"
        bad.write_text("procedure: unsettled\nsteps:\n  - orientations:\n      angles_deg: [[90, 0, 0]]\n"
                       "      sample: 5 s\n      settle: {hold: 1 s, timeout: 0.2 s}\n")
        assert control.request(sock, "submit", {"procedure": str(bad)})["ok"]
        hook = wait_for(lambda: notices("failed"), 30, "the 'failed' webhook")[0]
        assert "did not settle" in hook["message"] and hook["job"]["id"] == 3
        wait_for(lambda: mails("job 3 failed"), 20, "the 'failed' e-mail")

        # 4) a device fault while running: the rig is faulted, a notice says so
        fault["on"] = True
        assert control.request(sock, "submit", {"procedure": warm, "params": {"warmup": "10 min"}})["ok"]
        hook = wait_for(lambda: notices("faulted"), 30, "the 'faulted' webhook")[0]
        assert "another unit answers" in hook["message"] and hook["job"]["id"] == 4
        wait_for(lambda: mails("job 4 faulted"), 20, "the 'faulted' e-mail")
        assert control.request(sock, "status")["state"] == "faulted"
        assert not notices("interrupted") and not mails("interrupted")
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)


def test_a_dead_receiver_holds_up_nothing_and_is_logged(tmp_path):
    # bound and never listening: a connection to it is refused, and no other process can take
    # the port and answer while the test runs (a port looked up and closed could be)
    holder = bound_socket()
    dead = holder.getsockname()[1]
    cfg = derived_config(tmp_path, notifications={"webhook": {"url": f"http://127.0.0.1:{dead}/x", "timeout_s": 1}})
    base = Path(tempfile.mkdtemp(prefix="rigctl-notify-", dir="/tmp"))
    log = io.StringIO()
    d = Daemon(tmp_path / "runs", cfg, base / "s.sock", console=log,
               options=RunOptions(suspenders=SuspenderSettings(min_free_bytes=0)))
    d.start()
    try:
        for w in ("5 s", "6 s"):  # the second job starts while the first one's notice is still being tried
            assert control.request(d.socket_path, "submit", {"procedure": str(ROOT / "procedures" / "warmup.yaml"),
                                                             "params": {"warmup": w}})["ok"]
        wait_for(lambda: [j["state"] for j in control.request(d.socket_path, "queue")["jobs"]] == ["complete"] * 2,
                 30, "both jobs")
        assert log.getvalue().count("webhook notification not delivered") < 2  # the jobs did not wait for them
        wait_for(lambda: log.getvalue().count("webhook notification not delivered") == 2, 20, "two warnings")
    finally:
        d.stop("test over")
        shutil.rmtree(base, ignore_errors=True)
        holder.close()


@pytest.mark.parametrize("section, why", [
    ({"events": ["complete", "exploded"]}, "unknown event 'exploded'"),
    ({"webhook": {"url": "file:///etc/passwd"}}, "must be an http:// or https:// address"),
    ({"email": {"smtp_host": "x", "from": "rig@lab", "to": ["nobody"]}}, "'to' must list e-mail addresses"),
    ({"email": {"smtp_host": "x", "from": "rig@lab", "to": ["a@b"], "password": "hunter2"}}, "password"),
    ({"suspended_after_s": "-1 s"}, "suspended_after_s"),
])
def test_bad_notification_settings_name_file_and_line(tmp_path, section, why):
    cfg = derived_config(tmp_path, notifications=section)
    with pytest.raises(InputError) as e:
        load_config(cfg)
    text = str(e.value)
    assert why in text and str(cfg) in text and yaml.safe_load(cfg.read_text())["notifications"]
