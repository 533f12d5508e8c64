"""``dotshell lose-view RUN N ... --reason TEXT``: the operator marks views whose frames are bad
and cannot be re-captured as **lost** (:mod:`dotshell.run.lost`), and the run is processed
from the other views into a new generation, in one job.

The mark is recorded under the run's lock, before the processing: in ``manifest.json`` (the
view's ``lost``), in ``events.jsonl`` (a :class:`ViewLost` event per view) and in the job's
history (command ``lose-view``). The new generation's ``report.json`` lists them in
``lost_views``. The frames stay on disk, untouched. A run whose every view is captured or lost
becomes ``completed``, its ``reason`` naming the lost views; if the processing fails, the mark
stays (it is the operator's decision) and the run keeps its status and products, as after any
failed re-processing.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dotshell.errors import RunError
from dotshell.events import Event, EventBus
from dotshell.pipeline.engine import RunJob, process
from dotshell.plugins import PluginManager
from dotshell.run.frames import frames_on_disk
from dotshell.run.lost import is_lost, usable
from dotshell.run.store import RunStore


@dataclass(frozen=True)
class ViewLost(Event):
    """The operator marked ``view`` lost: processing goes on without it. ``frames_on_disk``:
    its whole frames then on disk (kept); ``was_complete``: whether it had been captured whole."""

    view: int
    angle_deg: float
    reason: str
    frames_on_disk: int
    was_complete: bool


def check_lose_request(store: RunStore, views: list[int], reason: str) -> list[int]:
    """The views to mark (sorted, each once), or a :class:`RunError` naming what is wrong:
    a view the run does not have, an empty reason, or no view left to process."""
    m = store.manifest
    n = len(m["views"])
    wrong = [v for v in views if not 0 <= v < n]
    if wrong:
        raise RunError(f"view {wrong[0]}: {store.root} has views 0 to {n - 1} (the N of "
                       "frames/view_NNN.tif).")
    if not reason.strip():
        raise RunError("--reason is empty: say why the view is lost (e.g. --reason 'stack cut "
                       "by a failed copy, sample since moved'); it is recorded in the run.")
    chosen = sorted(set(views))
    left = [v["index"] for v in m["views"] if usable(v) and v["index"] not in chosen]
    if not left:
        raise RunError(f"marking view{'s' if len(chosen) > 1 else ''} "
                       f"{', '.join(map(str, chosen))} of {store.root} lost leaves no captured "
                       "view to process; re-capture instead (`dotshell resume RUN --view N`).")
    return chosen


def _mark(job: RunJob, views: list[int], reason: str) -> None:
    """Record ``views`` lost in the manifest (one write) and the event log."""
    store = job.store
    m = store.manifest
    on_disk = frames_on_disk(store.root, m)
    marked = time.strftime("%Y-%m-%dT%H:%M:%S")
    entries = [dict(v) for v in m["views"]]
    for v in views:
        entries[v]["lost"] = {"reason": reason.strip(), "marked": marked,
                              "frames_on_disk": on_disk[v]}
    store.update_manifest(views=entries)
    for v in views:
        job.bus.emit(ViewLost(view=v, angle_deg=float(entries[v]["angle_deg"]),
                              reason=reason.strip(), frames_on_disk=on_disk[v],
                              was_complete=bool(entries[v]["complete"])))


def lose_views(run_dir: Path | str, views: list[int], reason: str, pm: PluginManager,
               bus: EventBus | None = None) -> dict[str, Any]:
    """Mark ``views`` of the run lost and process the run from the others (see the module
    docstring); returns the published report."""
    from dotshell.pipeline.scan import load_run_profile

    bus = bus or EventBus()
    store = RunStore.open(Path(run_dir))
    unsub = bus.subscribe(lambda ev: store.append_event(ev.to_dict()))
    try:
        chosen = check_lose_request(store, views, reason)
        already = [v for v in chosen if is_lost(store.manifest["views"][v])]
        if already:
            bus.info(f"view {', '.join(map(str, already))} was already marked lost; its reason "
                     "is replaced")
        profile = load_run_profile(store, pm)
        with RunJob(store, "lose-view", bus) as job:
            _mark(job, chosen, reason)
            return process(job, profile, pm, ("views",), {})
    finally:
        unsub()
        store.close()
