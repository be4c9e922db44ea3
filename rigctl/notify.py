"""Notices when a daemon job ends, fails, stays suspended too long or the rig faults: a webhook
(JSON POST) and/or an e-mail (SMTP), configured in the rig config's ``notifications:`` section
(docs/daemon.md). Sending happens on a thread of its own, so a slow or dead receiver never holds
up the rig; a notice that cannot be delivered is a warning in the daemon log (tried twice).
"""
from __future__ import annotations

import json
import queue
import smtplib
import socket
import ssl
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from email.message import EmailMessage
from pathlib import Path
from typing import Any

from . import schema as S
from .yamlio import LocDict

EVENTS = ("complete", "failed", "interrupted", "suspended", "faulted")
KEYS = ("events", "suspended_after_s", "webhook", "email")
WEBHOOK_KEYS = ("url", "timeout_s")
EMAIL_KEYS = ("smtp_host", "smtp_port", "from", "to", "starttls", "username", "password_file", "timeout_s")


@dataclass(frozen=True)
class NotifySettings:
    events: tuple[str, ...] = ("complete", "failed", "suspended", "faulted")
    suspended_after_s: float = 600.0   # wall seconds a job stays paused/suspended before a notice
    webhook_url: str = ""
    webhook_timeout_s: float = 10.0
    smtp_host: str = ""
    smtp_port: int = 25
    mail_from: str = ""
    mail_to: tuple[str, ...] = ()
    starttls: bool = False
    username: str = ""
    password_file: str = ""            # the password lives in its own file, never in the config
    smtp_timeout_s: float = 20.0
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def enabled(self) -> bool:
        return bool(self.webhook_url or self.smtp_host)


def notify_settings(m: LocDict) -> NotifySettings:
    """The ``notifications:`` section of a rig config (absent: nothing is sent)."""
    if m.get("notifications") is None:
        return NotifySettings()
    n = S.require_mapping(m["notifications"], "'notifications'", m, "notifications")
    S.check_keys(n, KEYS, "'notifications'")
    d = NotifySettings()
    events = tuple(S.get_list(n, "events", list(d.events)))
    for e in events:
        if e not in EVENTS:
            raise S.error(n, "events", f"'events': unknown event {e!r}", S.did_you_mean(str(e), EVENTS))
    after = S.get_duration(n, "suspended_after_s", d.suspended_after_s, positive=True)
    kw: dict[str, Any] = {"events": events, "suspended_after_s": float(after)}
    if n.get("webhook") is not None:
        w = S.require_mapping(n["webhook"], "'notifications.webhook'", n, "webhook")
        S.check_keys(w, WEBHOOK_KEYS, "'notifications.webhook'")
        url = S.get_str(w, "url")
        u = urllib.parse.urlsplit(url)
        if u.scheme not in ("http", "https") or not u.hostname:
            raise S.error(w, "url", f"'url' {url!r} must be an http:// or https:// address")
        kw.update(webhook_url=url, webhook_timeout_s=float(S.get_duration(w, "timeout_s", 10.0, positive=True)))
    if n.get("email") is not None:
        e = S.require_mapping(n["email"], "'notifications.email'", n, "email")
        S.check_keys(e, EMAIL_KEYS, "'notifications.email'")
        to = S.get_list(e, "to")
        if not to or not all(isinstance(a, str) and "@" in a and "\n" not in a for a in to):
            raise S.error(e, "to", "'to' must list e-mail addresses", "to: [lab@example.org]")
        sender = S.get_str(e, "from")
        if "@" not in sender or "\n" in sender:
            raise S.error(e, "from", f"'from' {sender!r} is not an e-mail address")
        pw = S.get_str(e, "password_file", "")
        if pw and not Path(pw).is_file():
            raise S.error(e, "password_file", f"'password_file' {pw} does not exist")
        kw.update(smtp_host=S.get_str(e, "smtp_host"),
                  smtp_port=int(S.get_number(e, "smtp_port", 25, minimum=1, maximum=65535, integer=True)),
                  mail_from=sender, mail_to=tuple(to), starttls=bool(S.get_bool(e, "starttls", False)),
                  username=S.get_str(e, "username", ""), password_file=pw,
                  smtp_timeout_s=float(S.get_duration(e, "timeout_s", 20.0, positive=True)))
    return NotifySettings(**kw)


def subject(notice: dict[str, Any]) -> str:
    job = notice.get("job") or {}
    what = Path(str(job.get("procedure") or job.get("run_dir") or "")).name
    head = f"job {job['id']} {notice['event']}" if job.get("id") is not None else notice["event"]
    return f"rigctl on {notice.get('rig', '?')}: {head}" + (f" ({what})" if what else "")


def body_text(notice: dict[str, Any]) -> str:
    job = notice.get("job") or {}
    lines = [subject(notice), "", f"event:    {notice['event']}", f"time:     {notice['utc']}",
             f"host:     {notice.get('host', '')}"]
    if notice.get("message"):
        lines.append(f"message:  {notice['message']}")
    for k in ("id", "procedure", "params", "run_dir", "state", "started_utc", "ended_utc"):
        if job.get(k) not in (None, "", {}):
            lines.append(f"job {k + ':':<13s}{job[k]}")
    return "\n".join(lines) + "\n"


class Notifier:
    """Queues notices and sends them from a background thread."""

    def __init__(self, settings: NotifySettings, rig: str, log: Callable[..., None]) -> None:
        self.s, self.rig, self.log = settings, rig, log
        self.q: queue.Queue[dict[str, Any] | None] = queue.Queue(maxsize=1000)
        self.sent: list[dict[str, Any]] = []   # what went out (the last 100), for status and tests
        self.thread = threading.Thread(target=self._run, name="rigctl-notify", daemon=True)
        self.started = False

    def start(self) -> None:
        if self.s.enabled and not self.started:
            self.thread.start()
            self.started = True

    def notify(self, event: str, message: str = "", job: dict[str, Any] | None = None) -> None:
        if not self.s.enabled or event not in self.s.events:
            return
        notice = {"event": event, "rig": self.rig, "host": socket.gethostname(), "message": message,
                  "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "job": job}
        try:
            self.q.put_nowait(notice)
        except queue.Full:
            self.log("warning", f"notification dropped (queue full): {subject(notice)}")

    def close(self, timeout: float = 10.0) -> None:
        """Send what is queued (up to ``timeout``), then stop."""
        if self.started:
            self.q.put(None)
            self.thread.join(timeout)

    def _run(self) -> None:
        while (notice := self.q.get()) is not None:
            for name, send in (("webhook", self._webhook if self.s.webhook_url else None),
                               ("e-mail", self._email if self.s.smtp_host else None)):
                if send is None:
                    continue
                for attempt in (1, 2):
                    try:
                        send(notice)
                        self.sent = (self.sent + [{"via": name, **notice}])[-100:]
                        break
                    except (OSError, smtplib.SMTPException, urllib.error.URLError, ValueError) as exc:
                        if attempt == 2:
                            self.log("warning", f"{name} notification not delivered ({subject(notice)}): "
                                                f"{type(exc).__name__}: {exc}")
                        else:
                            time.sleep(2.0)

    def _webhook(self, notice: dict[str, Any]) -> None:
        req = urllib.request.Request(self.s.webhook_url, data=json.dumps(notice, default=str).encode(),
                                     method="POST", headers={"Content-Type": "application/json",
                                                             "User-Agent": "rigctl-notify"})
        with urllib.request.urlopen(req, timeout=self.s.webhook_timeout_s) as r:
            if not 200 <= r.status < 300:
                raise OSError(f"HTTP {r.status}")

    def _email(self, notice: dict[str, Any]) -> None:
        msg = EmailMessage()
        msg["Subject"] = subject(notice)
        msg["From"] = self.s.mail_from
        msg["To"] = ", ".join(self.s.mail_to)
        msg.set_content(body_text(notice))
        with smtplib.SMTP(self.s.smtp_host, self.s.smtp_port, timeout=self.s.smtp_timeout_s) as smtp:
            if self.s.starttls:
                smtp.starttls(context=ssl.create_default_context())
            if self.s.username:
                pw = Path(self.s.password_file).read_text().strip() if self.s.password_file else ""
                smtp.login(self.s.username, pw)
            smtp.send_message(msg)
