"""Workers: which sim workers and trainers are on the bus and what each is doing (the hub's directory)."""

from __future__ import annotations

import time

HINT = """Workers join the studio's bus from this machine (the embedded default) or others
(`studio worker sim|train --connect tcp/<this host>:7447`, see docs/deployment.md)."""


def _ago(t: float) -> str:
    """How long ago ``t`` was, kept on one line (a no-break space between number and unit)."""
    s = max(0.0, time.time() - t)
    return (
        f"{s:.0f}\u00a0s" if s < 120 else f"{s / 60:.0f}\u00a0min" if s < 7200 else f"{s / 3600:.1f}\u00a0h"
    )


class WorkersPanel:
    """The *Workers* tab."""

    def __init__(self, tab):
        self.tab = tab
        gui = tab.client.gui
        gui.add_markdown(HINT)
        self.table = gui.add_markdown("Looking for workers…")
        self.jobs = gui.add_markdown("")
        self._shown = ""

    def describe(self) -> str:
        entries = self.tab.app.hub.directory.workers()
        if not entries:
            return "**No worker is connected.** Teleop, plans, rollouts and training wait for one."
        rows = [
            "| kind | worker | host | state | doing | sessions | offers | up\u00a0for |",
            "|---" * 8 + "|",
        ]
        for e in entries:
            st = e.status
            if st is None:
                rows.append(f"| {e.kind} | `{e.worker}` | ? | joining | | | | |")
                continue
            offers = ", ".join(st.job_kinds) or "—"
            if st.unavailable:
                offers += " (not: " + ", ".join(st.unavailable) + ")"
            doing = st.activity + (f" — job `{st.job}`" if st.job else "")
            rows.append(
                f"| {e.kind} | `{e.worker}` | {st.host} (pid {st.pid}) | {st.state} | {doing} | {st.sessions} "
                f"| {offers} | {_ago(st.started_at)} |"
            )
        rows.append("")
        rows.append(f"{len(entries)} worker{'' if len(entries) == 1 else 's'} on the bus.")
        return "\n".join(rows)

    def describe_jobs(self) -> str:
        active = [s for s in self.tab.app.hub.jobs.jobs() if not s.terminal]
        if not active:
            return "No job is queued or running."
        rows = ["| job | kind | state | worker | note |", "|---|---|---|---|---|"]
        for s in active[-12:]:
            rows.append(f"| `{s.job}` | {s.kind} | {s.state} | {s.worker or '—'} | {s.reason[:80]} |")
        return "\n".join(rows)

    def refresh(self) -> None:
        text = self.describe()
        jobs = self.describe_jobs()
        if text + jobs != self._shown:
            self._shown = text + jobs
            self.table.content = text
            self.jobs.content = jobs

    def close(self) -> None:
        pass
