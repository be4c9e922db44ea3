"""Notices when a daemon job ends, fails, stays suspended too long or the rig faults: a webhook
(JSON POST) and/or an e-mail (SMTP), configured in the rig config's ``notifications:`` section
(docs/daemon.md). Sending happens on a thread of its own, so a slow or dead receiver never holds
up the rig; a notice that cannot be delivered is a warning in the daemon log (tried twice).
"""
from __future__ import annotations

import json
import queue
import socket
import threading
import time
import urllib.parse
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .. import schema as S
from ..settings import Settings, duration, flag, number, parse, section, setting, text
from ..yamlio import LocDict

EVENTS = ("complete", "failed", "interrupted", "suspended", "faulted")


def _events(d: LocDict, key: str, default: tuple[str, ...]) -> tuple[str, ...]:
    events = tuple(S.get_list(d, key, list(default)))
    for ev in events:
        if ev not in EVENTS:
            raise S.error(d, key, f"'events': unknown event {ev!r}", S.did_you_mean(str(ev), EVENTS))
    return events


def _addresses(d: LocDict, key: str, default: Any = ...) -> tuple[str, ...]:
    to = S.get_list(d, key, default)
    if not to or not all(isinstance(a, str) and "@" in a and "\n" not in a for a in to):
        raise S.error(d, key, "'to' must list e-mail addresses", "to: [lab@example.org]")
    return tuple(to)


def _subsection(cls: type[Settings], what: str) -> Any:
    """A nested section read by the same validator (null: absent)."""
    def read(d: LocDict, key: str, default: Any) -> Any:
        if d[key] is None:
            return default
        return parse(cls, S.require_mapping(d[key], what, d, key), what)
    return setting(None, read=read)


@dataclass(frozen=True, kw_only=True)
class WebhookSettings(Settings):
    """``notifications.webhook``: a JSON POST to ``url`` per notice."""

    url: str = text()
    timeout_s: float = duration(10.0, positive=True)

    def check(self, d: LocDict) -> None:
        u = urllib.parse.urlsplit(self.url)
        if u.scheme not in ("http", "https") or not u.hostname:
            raise S.error(d, "url", f"'url' {self.url!r} must be an http:// or https:// address")


@dataclass(frozen=True, kw_only=True)
class EmailSettings(Settings):
    """``notifications.email``: one e-mail per notice over SMTP (the password, if any, in a file
    of its own, never in the config)."""

    smtp_host: str = text()
    smtp_port: int = number(25, minimum=1, maximum=65535, integer=True)
    mail_from: str = text(key="from")
    mail_to: tuple[str, ...] = setting(read=_addresses, key="to")
    starttls: bool = flag(False)
    username: str = text("")
    password_file: str = text("")
    timeout_s: float = duration(20.0, positive=True)

    def check(self, d: LocDict) -> None:
        if "@" not in self.mail_from or "\n" in self.mail_from:
            raise S.error(d, "from", f"'from' {self.mail_from!r} is not an e-mail address")
        if self.password_file and not Path(self.password_file).is_file():
            raise S.error(d, "password_file", f"'password_file' {self.password_file} does not exist")


@dataclass(frozen=True, kw_only=True)
class NotifySettings(Settings):
    """The ``notifications:`` section of a rig config (rigctl.settings.parse)."""

    events: tuple[str, ...] = setting(("complete", "failed", "suspended", "faulted"), read=_events)
    #: wall seconds a job stays paused/suspended before a notice
    suspended_after_s: float = duration(600.0, positive=True)
    webhook: WebhookSettings | None = _subsection(WebhookSettings, "'notifications.webhook'")
    email: EmailSettings | None = _subsection(EmailSettings, "'notifications.email'")
    extra: dict[str, Any] = field(default_factory=dict, metadata={"internal": True})

    @property
    def enabled(self) -> bool:
        return self.webhook is not None or self.email is not None


def notify_settings(m: LocDict) -> NotifySettings:
    """The ``notifications:`` section of a rig config (absent: nothing is sent)."""
    return section(m, "notifications", NotifySettings)


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
            for name, send in (("webhook", self._webhook if self.s.webhook else None),
                               ("e-mail", self._email if self.s.email else None)):
                if send is None:
                    continue
                for attempt in (1, 2):
                    try:
                        send(notice)
                        self.sent = (self.sent + [{"via": name, **notice}])[-100:]
                        break
                    # smtplib.SMTPException and urllib.error.URLError are OSErrors
                    except (OSError, ValueError) as exc:
                        if attempt == 2:
                            self.log("warning", f"{name} notification not delivered ({subject(notice)}): "
                                                f"{type(exc).__name__}: {exc}")
                        else:
                            time.sleep(2.0)

    def _webhook(self, notice: dict[str, Any]) -> None:
        import urllib.request  # here, not at import: every rig config loads this module

        w = self.s.webhook
        assert w is not None
        req = urllib.request.Request(w.url, data=json.dumps(notice, default=str).encode(),
                                     method="POST", headers={"Content-Type": "application/json",
                                                             "User-Agent": "rigctl-notify"})
        with urllib.request.urlopen(req, timeout=w.timeout_s) as r:
            if not 200 <= r.status < 300:
                raise OSError(f"HTTP {r.status}")

    def _email(self, notice: dict[str, Any]) -> None:
        import smtplib  # here, not at import: smtplib, ssl and email cost ~0.1 s of CPU per process
        import ssl
        from email.message import EmailMessage

        e = self.s.email
        assert e is not None
        msg = EmailMessage()
        msg["Subject"] = subject(notice)
        msg["From"] = e.mail_from
        msg["To"] = ", ".join(e.mail_to)
        msg.set_content(body_text(notice))
        with smtplib.SMTP(e.smtp_host, e.smtp_port, timeout=e.timeout_s) as smtp:
            if e.starttls:
                smtp.starttls(context=ssl.create_default_context())
            if e.username:
                pw = Path(e.password_file).read_text().strip() if e.password_file else ""
                smtp.login(e.username, pw)
            smtp.send_message(msg)
