"""Plain, aligned text for the daemon's client verbs (``rigctl status``, ``queue``, ``logs``, ...):
pure functions of the daemon's JSON replies (the same replies ``--json`` prints whole)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from ..units import format_duration


def _what(job: dict[str, Any]) -> str:
    if job.get("kind") == "resume":
        return f"resume {Path(str(job.get('run_dir') or '')).name}"
    return Path(str(job.get("procedure") or "")).name


def _params(job: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in (job.get("params") or {}).items())


def _utc(text: str) -> str:
    """'2026-11-26T05:59:37.49Z' -> '2026-11-26 05:59:37'."""
    return text[:19].replace("T", " ") if text else ""


def _one_line(text: Any, width: int | None = None) -> str:
    s = " / ".join(part.strip() for part in str(text).splitlines() if part.strip())
    return s if width is None or len(s) <= width else s[: width - 3] + "..."


def status_text(r: dict[str, Any]) -> str:
    """``rigctl status``: one fact per line, labels aligned."""
    rows: list[tuple[str, str]] = []
    state = str(r.get("state"))
    since = str(r.get("since_utc", ""))[11:19]
    why = f" ({r['reason']})" if r.get("reason") else ""
    rows.append(("state", f"{state} since {since}Z{why}" if since else state + why))
    job = r.get("job")
    if job:
        extra = f", run {Path(job['run_dir']).name}" if job.get("run_dir") else ""
        params = f" [{_params(job)}]" if job.get("params") else ""
        rows.append(("job", f"{job['id']}: {_what(job)}{params}{extra}"))
    else:
        rows.append(("job", "none"))
    if r.get("step"):
        rows.append(("step", " ".join(str(r["step"]).split())))
    if "remaining_s" in r:
        rows.append(("progress", f"{100 * float(r.get('step_fraction') or 0):.0f} % of the step, "
                                 f"about {format_duration(float(r['remaining_s']))} of rig time left"))
    if "imu_samples" in r:
        rows.append(("recorded", f"{int(r['imu_samples']):,} IMU samples, {int(r.get('segments') or 0)} segments"))
    if job:
        sus = r.get("suspenders") or {}
        rows.append(("suspended", "; ".join(f"{k}: {v}" for k, v in sus.items()) if sus else "no"))
        if r.get("deferred_pause"):
            rows.append(("pause", "requested for the end of this step"))
    rows.append(("queue", f"{r.get('queued', 0)} queued, queue {'running' if r.get('queue_running', True) else 'stopped'}"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k + ':':<{width + 1}}  {v}" for k, v in rows)


def jobs_table(jobs: list[dict[str, Any]], queued: list[int] | None = None) -> str:
    """A table of jobs: queued ones first in queue order (with their place), then the rest."""
    queued = list(queued or [])
    by_id = {j["id"]: j for j in jobs}
    order = [by_id[i] for i in queued if i in by_id] + [j for j in jobs if j["id"] not in queued]
    if not order:
        return "no jobs"
    head = ("PLACE", "JOB", "STATE", "WHAT", "PARAMETERS", "SUBMITTED (UTC)", "ENDED (UTC)", "MESSAGE")
    rows = []
    for j in order:
        place = str(queued.index(j["id"]) + 1) if j["id"] in queued else ""
        rows.append((place, str(j["id"]), str(j.get("state", "")), _what(j), _params(j),
                     _utc(j.get("submitted_utc", "")), _utc(j.get("ended_utc", "")),
                     _one_line(j.get("message", ""), 60)))
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    right = {0, 1}

    def line(cells) -> str:
        return "  ".join(c.rjust(w) if i in right else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths))).rstrip()

    return "\n".join([line(head), *(line(r) for r in rows)])


def log_line(raw: str) -> str:
    """One run-log record (a JSON line) as one printed line: UTC, kind, message."""
    try:
        rec = json.loads(raw)
    except ValueError:
        return _one_line(raw)
    return f"{rec.get('utc', '')} {rec.get('kind', ''):8s} {_one_line(rec.get('message', ''))}"


def reply_text(cmd: str, r: dict[str, Any]) -> str:
    """The text for an accepted request ``cmd`` (ok replies only)."""
    if cmd == "status":
        return status_text(r)
    if cmd == "queue":
        return jobs_table(r.get("jobs", []), r.get("queued", [])) + \
            f"\nqueue {'running' if r.get('queue_running', True) else 'stopped'}, {len(r.get('queued', []))} queued"
    if cmd == "history":
        return jobs_table(r.get("jobs", []))
    if cmd == "logs":
        return "\n".join(log_line(x) for x in r.get("lines", []))
    if cmd == "submit":
        return f"job {r['job']} queued at place {r['position']}"
    if cmd in ("queue_remove", "queue_move"):
        return "queue: " + (", ".join(str(i) for i in r.get("queued", [])) or "empty")
    if cmd == "queue_clear":
        return f"removed {len(r.get('removed', []))} queued jobs"
    if cmd == "queue_stop":
        run = r.get("running_job")
        return "queue stopped: no new job starts" + (f" (job {run} runs to its end)" if run else "")
    if cmd == "queue_start":
        return "queue started"
    if cmd == "abort":
        return f"aborting the running job; {r.get('note', '')}".rstrip("; ")
    if cmd == "pause":
        return "pausing at the end of the step in flight" if r.get("deferred") else "pausing now (the step in flight re-runs)"
    if cmd == "resume" and "job" in r:
        return f"job {r['job']} queued: resume"
    parts = [f"{cmd}: ok"] + [f"{k} {v}" for k, v in r.items() if k not in ("ok",)]
    return ", ".join(parts)
