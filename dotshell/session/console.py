"""The scripting facade: one live session of the instrument — a profile, its rig, the last run.

Every front end that operates a rig interactively goes through :class:`Session`: the Textual
TUI (``dotshell tui``), its embedded Python console and headless scripts (``dotshell script``).
Workflow logic lives here and in :mod:`dotshell.pipeline`, never in widgets::

    s = Session("profiles/sim-metal-cylinder.toml")
    s.connect()
    s.jog(15)                      # degrees, relative
    snap = s.snap()                # frame array + PNG preview path
    run = s.scan()                 # blocks; s.scan(wait=False) returns a ScanJob
    run.report["validation"]["mean_rel_error_pct"]

Device actions refuse while a scan is running (:class:`SessionBusy`); ``pause()``,
``resume()``, ``abort()`` and ``stop()`` steer a scan from any thread. Everything the session
does is published on :attr:`Session.bus` (the scan's events, :class:`PreviewSaved`, a log line
for every rig action). The rig server (:mod:`dotshell.server`) holds one Session for all front
ends. Importing this module is cheap (no numpy, no plugins): front ends that only decode its
events import it too.
"""

from __future__ import annotations

import re
import sys
import threading
import time
import types
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Sequence, overload

from dotshell.errors import DeviceError, DotshellError, ProfileError, RunError
from dotshell.events import Event, EventBus, ScanFinished, ScanStarted, ViewCaptured
from dotshell.run.layout import RunLayout

if TYPE_CHECKING:
    import numpy as np

    from dotshell.plugins import PluginManager
    from dotshell.profile.loader import Profile
    from dotshell.rig.assembly import Rig

#: Session states: no scan, scanning, paused between frames, abort requested.
STATES = ("idle", "running", "paused", "stopping")


class SessionBusy(DotshellError):
    """The action needs the rig, but a scan is using it."""


@dataclass(frozen=True)
class PreviewSaved(Event):
    """A preview PNG was written: ``kind`` is ``snap``, ``frame`` (latest view of a scan),
    ``columns`` (decoded projector columns) or ``cloud``; ``view`` is -1 when not a view
    (0-based). ``stats`` describes the raw frame behind a ``snap`` or ``frame`` preview
    (:func:`frame_stats`), empty otherwise."""

    kind: str
    path: str
    view: int = -1
    stats: dict[str, Any] = field(default_factory=dict)


#: The lowest level of the session's log lines a console or script shows while it runs
#: (``debug`` adds a line per frame; ``off`` shows none); :meth:`Session.log_level`.
LOG_LEVEL = "info"
LOG_LEVELS = ("debug", "info", "warning", "error", "off")
#: Bins of the histogram in :func:`frame_stats`.
HISTOGRAM_BINS = 32


def frame_stats(frame: np.ndarray, bit_depth: int | None = None) -> dict[str, Any]:
    """What a person checks on a raw frame: its size, minimum, maximum and mean (DN), the share
    of saturated pixels (at full scale, ``2**bit_depth - 1``; the dtype's maximum when the bit
    depth is unknown), in percent, and a histogram over 0..full scale (counts)."""
    import numpy as np

    full = (1 << bit_depth) - 1 if bit_depth else int(np.iinfo(frame.dtype).max) \
        if np.issubdtype(frame.dtype, np.integer) else float(frame.max())
    counts, _ = np.histogram(frame, bins=HISTOGRAM_BINS, range=(0, max(full, 1)))
    return {"width": int(frame.shape[1]), "height": int(frame.shape[0]),
            "min": float(frame.min()), "max": float(frame.max()), "mean": float(frame.mean()),
            "full_scale": float(full),
            "saturated_pct": float(100.0 * np.count_nonzero(frame >= full) / frame.size),
            "histogram": counts.astype(int).tolist()}


@dataclass
class Snapshot:
    """One frame taken with :meth:`Session.snap`: the raw frame, its lossless PNG (``path``)
    and the 8-bit stretched preview PNG (``preview``)."""

    frame: np.ndarray
    path: Path
    preview: Path
    angle_deg: float


@dataclass
class DecodeResult:
    """A pattern sequence captured and decoded at the current stage angle."""

    decoded_pixels: int
    total_pixels: int
    preview: Path


class Run:
    """A run directory read back: status, manifest, report, frames, cloud."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root)

    def __repr__(self) -> str:
        return f"Run({str(self.root)!r}, status={self.status!r})"

    def _json(self, name: str) -> dict[str, Any]:
        from dotshell.run.store import RunStore

        p = self.root / name
        return RunStore(self.root).read_json(name) if p.is_file() else {}

    @property
    def manifest(self) -> dict[str, Any]:
        return self._json(RunLayout.MANIFEST)

    @property
    def report(self) -> dict[str, Any]:
        return self._json(RunLayout.REPORT)

    @property
    def status(self) -> str:
        """``running``, ``completed``, ``aborted``, ``failed``, ``interrupted`` (recorded
        ``running`` but no process writes it any more) or ``unknown``."""
        return self.status_and_reason()[0]

    def status_and_reason(self) -> tuple[str, str]:
        """The run's status as it truly is, and why when it is not ``completed``."""
        from dotshell.run.store import RunStore

        if not (self.root / RunLayout.MANIFEST).is_file():
            return "unknown", f"{self.root} has no manifest.json"
        try:
            return RunStore(self.root).status()
        except RunError as exc:  # a damaged manifest: say so rather than fail the caller
            return "unknown", str(exc)

    def frame_count(self) -> int:
        """Frames on disk over all views."""
        return sum(v["frames"] for v in self.manifest.get("views", []))

    def frames(self, view: int) -> np.ndarray:
        """The frames of a view, (frames, height, width) in capture order, as captured."""
        from dotshell.run.store import RunStore

        return RunStore(self.root).read_frames(view)

    def events(self) -> list[dict[str, Any]]:
        from dotshell.run.store import RunStore

        return RunStore(self.root).events()

    def cloud(self) -> np.ndarray:
        """The merged cloud, (N, 3) float in mm (sample/stage frame)."""
        from dotshell.run.ply import read_ply

        p = self.root / RunLayout.CLOUD
        if not p.is_file():
            raise RunError(f"{p} does not exist (status {self.status}); only completed or "
                           "re-processed runs have a merged cloud.")
        return read_ply(p)[0]


class ScanJob:
    """A scan running on a background thread (``Session.scan(wait=False)``)."""

    def __init__(self, target: Callable[[], Run]) -> None:
        self.result: Run | None = None
        self.error: BaseException | None = None
        self.started = time.time()
        self.thread = threading.Thread(target=self._run, args=(target,), name="dotshell-scan",
                                       daemon=True)
        self.thread.start()

    def _run(self, target: Callable[[], Run]) -> None:
        try:
            self.result = target()
        except BaseException as exc:  # handed to whoever waits
            self.error = exc

    @property
    def done(self) -> bool:
        return not self.thread.is_alive()

    def __repr__(self) -> str:
        if not self.done:
            return f"ScanJob(running for {time.time() - self.started:.0f} s; wait() returns the Run)"
        if self.error is not None:
            return f"ScanJob(failed: {type(self.error).__name__}: {self.error})"
        return f"ScanJob(done: {self.result!r})"

    def wait(self, timeout: float | None = None) -> Run:
        """The finished run; re-raises the scan's error. TimeoutError if still running."""
        self.thread.join(timeout)
        if self.thread.is_alive():
            raise TimeoutError(f"the scan is still running after {timeout} s")
        if self.error is not None:
            raise self.error
        assert self.result is not None
        return self.result


def _next_free(directory: Path, stem: str) -> int:
    """1 + the highest ``<stem>_NNNN`` number in ``directory`` (file names stay short and
    predictable: snap_0001.png, snap_0002.png, ...)."""
    pat = re.compile(rf"{re.escape(stem)}_(\d{{4}})")
    nums = [int(m.group(1)) for p in directory.glob(f"{stem}_*") if (m := pat.match(p.name))]
    return max(nums, default=0) + 1


class Session:
    """A live session: plugin manager, profile, rig (built on load, connected on demand), the
    last run, and the scan control (pause, resume, abort, stop).

    Args:
        profile: a profile file, a validated :class:`Profile`, or None (load one later).
        pm: the plugin manager (default: every installed plugin).
        out_dir: parent directory of runs and of ``snapshots/`` (snap and decode previews).
        overrides: ``KEY=VALUE`` profile overrides, as ``--set`` on the command line.
        bus: the event bus to publish on (default: a new one).
    """

    def __init__(self, profile: Profile | str | Path | None = None, *,
                 pm: PluginManager | None = None, out_dir: Path | str = "runs",
                 overrides: Sequence[str] = (), bus: EventBus | None = None) -> None:
        if pm is None:
            from dotshell.plugins import get_plugin_manager

            pm = get_plugin_manager()
        self.pm = pm
        self.out_dir = Path(out_dir)
        self.bus = bus or EventBus()
        self.profile: Profile | None = None
        self.profile_path: Path | None = None
        self.rig: Rig | None = None
        self.run: Run | None = None
        self.projected: str | None = None
        self.job: ScanJob | None = None
        self._state = "idle"
        self._lock = threading.RLock()  # device I/O: one action at a time
        self._state_lock = threading.Lock()  # scan state changes, never held during I/O
        self._stop = threading.Event()
        self._running = threading.Event()
        self._coding: Any = None
        self._patterns: dict[str, np.ndarray] | None = None
        self._live: dict[str, Any] = {}
        self._namespaces: list[weakref.ref] = []
        self._log_level = LOG_LEVEL
        self.bus.subscribe(self._live_preview)
        if profile is not None:
            self.load(profile, overrides)

    def __repr__(self) -> str:
        name = self.profile.name if self.profile else "no profile"
        rig = "connected" if self.connected else "not connected"
        return f"Session({name}, rig {rig}, {self._state}, out {str(self.out_dir)!r})"

    # ---- profile ------------------------------------------------------------------------------

    def load(self, profile: Profile | str | Path, overrides: Sequence[str] = ()) -> Profile:
        """Load a profile (file or :class:`Profile`); closes the previous rig."""
        from dotshell.profile.loader import Profile, apply_overrides, load_profile, validate_profile
        from dotshell.rig.assembly import Rig

        with self._lock:
            self._require_idle("load another profile")
            if isinstance(profile, Profile):
                prof = profile
                if overrides:
                    prof = validate_profile(apply_overrides(profile.raw(), list(overrides),
                                                            profile.source),
                                            self.pm, profile.source, profile.base_dir)
            else:
                prof = load_profile(profile, self.pm, list(overrides))
                self.profile_path = Path(profile)
            rig = Rig(prof, self.pm)
            self.disconnect()
            self.profile, self.rig = prof, rig
            self._coding, self._patterns, self.projected = None, None, None
        self.bus.info(f"profile {prof.name} loaded from {prof.source}"
                      + (f" with {', '.join(overrides)}" if overrides else ""))
        self._refresh_namespaces()
        return prof

    def set(self, *overrides: str) -> Profile:
        """Change profile keys (``"scan.views=4"``, TOML values); rebuilds the rig and
        reconnects it if it was connected."""
        prof = self._require_profile()
        was_connected = self.connected
        self.load(prof, overrides)
        if was_connected:
            self.connect()
        return self.profile  # type: ignore[return-value]

    def configure(self, *, views: int | None = None, exposure_ms: float | None = None,
                  pdi_angles_deg: Sequence[float] | None = None,
                  out_dir: Path | str | None = None) -> Profile | None:
        """Change the next scan's settings — ``views`` (equally spaced; explicit angles are
        dropped), camera exposure (ms), the PDI analyzer angles (parallel, perpendicular;
        degrees) and the output directory — without rebuilding or reconnecting the rig. The
        profile the scan runs with (and records in the run) carries them. The profile's keys
        wait until no scan runs; the output directory applies to the next scan at once."""
        overrides, said = [], []
        if views is not None:
            overrides += [f"scan.views={int(views)}", "scan.angles_deg=[]"]
            said.append(f"{int(views)} views")
        if exposure_ms is not None:
            overrides.append(f"scan.exposure_ms={float(exposure_ms)!r}")
            said.append(f"exposure {float(exposure_ms):g} ms")
        if pdi_angles_deg is not None:
            angles = [float(a) for a in pdi_angles_deg]
            overrides.append(f"scan.pdi_angles_deg={angles!r}")
            said.append(f"analyzer angles {', '.join(f'{a:g}°' for a in angles)}")
        if overrides:
            self._retune(overrides)
        if out_dir is not None:
            self.out_dir = Path(out_dir).expanduser()
            said.append(f"output directory {self.out_dir}")
        if said:
            self.bus.info(f"scan settings: {'; '.join(said)}")
        return self.profile

    def _retune(self, overrides: list[str], then: Callable[[], None] | None = None) -> None:
        """Use the profile with ``scan.*`` keys changed, the rig kept (its devices are the
        same); ``then()`` runs once the new keys are valid, before they are used."""
        from dotshell.profile.loader import apply_overrides, validate_profile

        with self._lock:
            prof = self._require_profile()
            self._require_idle("change the scan's settings")
            new = validate_profile(apply_overrides(prof.raw(), overrides, prof.source),
                                   self.pm, prof.source, prof.base_dir)
            if then is not None:
                then()
            self.profile = new
            self.rig.profile = new  # type: ignore[union-attr]
        self._refresh_namespaces()

    def _require_profile(self) -> Profile:
        if self.profile is None or self.rig is None:
            raise ProfileError("no profile is loaded: load one with session.load(PATH) (in the "
                               "TUI: ctrl+o), e.g. profiles/sim-metal-cylinder.toml.")
        return self.profile

    # ---- state --------------------------------------------------------------------------------

    @property
    def state(self) -> str:
        """One of :data:`STATES`."""
        return self._state

    @property
    def scanning(self) -> bool:
        return self._state != "idle"

    def _require_idle(self, action: str) -> None:
        if self.scanning:
            raise SessionBusy(f"cannot {action} while a scan is {self._state}; wait for it, or "
                              "abort it first (session.abort(), in the TUI: x).")

    # ---- devices ------------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        """True when every device of the rig is connected."""
        rig = self.rig
        return rig is not None and bool(rig.devices) and len(rig.connected) == len(rig.devices)

    def connect(self) -> dict[str, dict[str, Any]]:
        """Connect every device; returns their status."""
        with self._lock:
            self._require_idle("connect")
            self._require_profile()
            self.rig.connect()  # type: ignore[union-attr]
        self.bus.info(f"rig connected: {', '.join(self.rig.connected)}")  # type: ignore[union-attr]
        return self.status()

    def disconnect(self) -> None:
        """Close every device (safe when not connected)."""
        with self._lock:
            self._require_idle("disconnect")
            if self.rig is not None and self.rig.connected:
                self.rig.close()
                self.projected = None
                self.bus.info("rig disconnected")

    def devices(self) -> list[dict[str, Any]]:
        """One row per device role of the profile: role, backend, connected, status."""
        from dotshell.profile.loader import DEVICE_ROLES

        if self.profile is None or self.rig is None:
            return []
        status = self.rig.status()
        rows = []
        for role in DEVICE_ROLES:
            section = self.profile.role(role)
            if section is None:
                continue
            rows.append({"role": role, "backend": section["backend"],
                         "connected": role in self.rig.connected, "status": status.get(role, {})})
        return rows

    def status(self) -> dict[str, dict[str, Any]]:
        """Live status of every device by role (empty without a profile)."""
        return {} if self.rig is None else self.rig.status()

    def _device(self, role: str, action: str) -> Any:
        self._require_idle(action)
        self._require_profile()
        dev = self.rig.devices.get(role)  # type: ignore[union-attr]
        if dev is None:
            raise DeviceError(f"cannot {action}: profile {self.profile.name} has no [{role}] "  # type: ignore[union-attr]
                              f"device; add a [{role}] section with a backend.")
        if role not in self.rig.connected:  # type: ignore[union-attr]
            raise DeviceError(f"cannot {action}: the {role} is not connected; connect the rig "
                              "first (connect(), in the TUI: c).")
        return dev

    def move_to(self, degrees: float) -> float:
        """Rotate the stage to an absolute angle; returns the angle reached (degrees)."""
        with self._lock:
            stage = self._device("stage", "move the stage")
            stage.move_to(float(degrees))
            reached = float(stage.position)
        self.bus.info(f"stage moved to {reached:.2f}°")
        return reached

    def home(self, role: str = "stage") -> float | None:
        """Home the stage (or ``role``): find its reference position; the angle afterwards."""
        with self._lock:
            self._device(role, f"home the {role}")
            reached = self.rig.home(role)  # type: ignore[union-attr]
        self.bus.info(f"{role} homed" + (f": at {reached:.2f}°" if reached is not None else ""))
        return reached

    def jog(self, degrees: float) -> float:
        """Rotate the stage by ``degrees`` (relative); returns the angle reached."""
        with self._lock:
            stage = self._device("stage", "jog the stage")
            start = float(stage.position)
            stage.move_to(start + float(degrees))
            reached = float(stage.position)
        self.bus.info(f"stage jogged {float(degrees):+.2f}° from {start:.2f}° to {reached:.2f}°")
        return reached

    def set_analyzer(self, degrees: float) -> float:
        """Set the analyzer's transmission axis (degrees)."""
        with self._lock:
            self._device("analyzer", "set the analyzer").set_angle(float(degrees))
        self.bus.info(f"analyzer set to {float(degrees):.2f}°")
        return float(degrees)

    def set_exposure(self, ms: float) -> float:
        """Set the camera exposure (ms), for cameras with exposure control — now, when the
        camera is connected, and for the scans that follow (``scan.exposure_ms``)."""
        from dotshell.devices import ExposureControl

        with self._lock:
            prof = self._require_profile()
            self._require_idle("set the exposure")
            cam = self.rig.devices.get("camera") if "camera" in self.rig.connected else None  # type: ignore[union-attr]
            if cam is not None and not isinstance(cam, ExposureControl):
                raise DeviceError(f"the camera ({prof.required_role('camera')['backend']}) has no "
                                  "exposure control.")
            # the value is checked as a profile key first: a refused one never reaches the camera
            self._retune([f"scan.exposure_ms={float(ms)!r}"],
                         then=(lambda: cam.set_exposure(float(ms))) if cam is not None else None)
        self.bus.info(f"camera exposure set to {float(ms):g} ms" + (
            "" if cam is not None else " for the scans (the camera is not connected)"))
        return float(ms)

    def stop(self) -> None:
        """Stop now, from any thread, without waiting for the action under way (a move holds
        the session): every device that can move is stopped (:meth:`dotshell.rig.assembly.Rig.stop`),
        then a running scan is aborted cleanly (frames kept). Safe when nothing moves."""
        rig = self.rig
        if rig is not None and rig.connected:
            rig.stop()
            self.bus.warn("stop: every device that can move was told to stop")
        self.abort()

    def log_level(self, level: str | None = None) -> str:
        """The lowest level of the session's log lines shown in the console (while an input
        runs) and by ``dotshell script``: ``debug``, ``info`` (default: progress, not a line
        per frame), ``warning``, ``error`` or ``off``; without an argument, the level now."""
        if level is not None:
            if level not in LOG_LEVELS:
                raise DotshellError(f"log_level({level!r}): choose one of "
                                    f"{', '.join(LOG_LEVELS[:-1])} or off.")
            self._log_level = level
        return self._log_level

    def shows(self, level: str) -> bool:
        """Whether a log line of ``level`` is shown at :meth:`log_level`."""
        if self._log_level == "off":
            return False
        rank = LOG_LEVELS.index(level) if level in LOG_LEVELS[:-1] else 1
        return rank >= LOG_LEVELS.index(self._log_level)

    def halt(self) -> str:
        """The stop key: stop motion, never abort. During a scan the scan is paused before its
        next frame (the move under way ends where the run says it does, so every frame is
        taken where it is recorded; ``resume()`` goes on, ``abort()`` ends it); otherwise every
        device that can move is stopped now. Returns ``"paused"`` (or ``"stopping"`` for a scan
        being aborted already) or ``"stopped"``."""
        if self._transition(("running",), "paused"):
            self._running.clear()
            self.bus.warn("stop key: the scan pauses before its next frame (resume goes on, "
                          "abort ends it)")
            return "paused"
        if self.scanning:
            return self._state  # paused or stopping already: nothing moves after this frame
        rig = self.rig
        if rig is not None and rig.connected:
            rig.stop()
            self.bus.warn("stop: every device that can move was told to stop")
        return "stopped"

    # ---- patterns, frames, decoding -------------------------------------------------------------

    def _coding_patterns(self) -> dict[str, np.ndarray]:
        if self._patterns is None:
            from dotshell.pipeline.steps import make_coding

            self._coding = make_coding(self._require_profile(), self.pm)
            size = self.rig.projector.resolution  # type: ignore[union-attr]
            self._patterns = {p.name: p.image for p in self._coding.patterns(size)}
        return self._patterns

    def patterns(self) -> list[str]:
        """Names of the coding's patterns for this projector, in projection order."""
        return list(self._coding_patterns())

    def project(self, name: str) -> str:
        """Show one of the coding's patterns (see :meth:`patterns`) on the projector."""
        with self._lock:
            proj = self._device("projector", "project a pattern")
            pats = self._coding_patterns()
            if name not in pats:
                raise DeviceError(f"no pattern {name!r} in the {self.profile.required_role('coding')['backend']} "  # type: ignore[union-attr]
                                  f"coding; choose one of {', '.join(pats)}.")
            proj.show(pats[name])
            self.projected = name
        self.bus.info(f"projector shows pattern {name}")
        return name

    def _snapshot_dir(self) -> Path:
        d = self.out_dir / "snapshots"
        d.mkdir(parents=True, exist_ok=True)
        return d

    def snap(self) -> Snapshot:
        """Capture one frame with the current pattern; writes ``snapshots/snap_NNNN.png``
        (lossless) and ``snap_NNNN_preview.png`` (8-bit) under the output directory."""
        import cv2

        from dotshell.render.previews import frame_preview
        from dotshell.run.store import atomic_write_bytes

        with self._lock:
            camera = self._device("camera", "snap a frame")
            frame = camera.capture()
            angle = float(self.rig.stage.position) if "stage" in self.rig.connected else 0.0  # type: ignore[union-attr]
        d = self._snapshot_dir()
        n = _next_free(d, "snap")
        raw = d / f"snap_{n:04d}.png"
        ok, buf = cv2.imencode(".png", frame)
        if not ok:
            raise RunError(f"could not encode {raw}")
        atomic_write_bytes(raw, buf.tobytes())
        preview = frame_preview(frame, d / f"snap_{n:04d}_preview.png")
        stats = frame_stats(frame, getattr(camera, "bit_depth", None))
        self.bus.info(f"snap at {angle:.2f}° (pattern {self.projected or 'none'}): mean "
                      f"{stats['mean']:.0f} DN, {stats['saturated_pct']:.2f} % saturated → {raw}")
        self.bus.emit(PreviewSaved(kind="snap", path=str(preview), stats=stats))
        return Snapshot(frame, raw, preview, angle)

    def decode(self) -> DecodeResult:
        """Project the whole coding sequence at the current stage angle, decode it and write
        the projector-column map (``snapshots/decode_NNNN.png``) — a focus/alignment check."""
        from dotshell.render.previews import column_map_preview

        with self._lock:
            cam = self._device("camera", "decode")
            proj = self._device("projector", "decode")
            pats = self._coding_patterns()
            frames = []
            for image in pats.values():
                proj.show(image)
                frames.append(cam.capture())
            self.projected = list(pats)[-1]
        corr = self._coding.decode(frames, proj.resolution)
        d = self._snapshot_dir()
        path = column_map_preview(corr.column, corr.valid, proj.resolution[0],
                                  d / f"decode_{_next_free(d, 'decode'):04d}.png")
        result = DecodeResult(int(corr.valid.sum()), int(corr.valid.size), path)
        self.bus.info(f"decode map: {result.decoded_pixels} of {result.total_pixels} pixels "
                      f"decoded → {path}")
        self.bus.emit(PreviewSaved(kind="columns", path=str(path)))
        return result

    # ---- scans ----------------------------------------------------------------------------------

    @overload
    def scan(self, wait: Literal[True] = ..., out: Path | str | None = None,
             calibration: Path | str | None = None) -> Run: ...

    @overload
    def scan(self, wait: Literal[False], out: Path | str | None = None,
             calibration: Path | str | None = None) -> ScanJob: ...

    def scan(self, wait: bool = True, out: Path | str | None = None,
             calibration: Path | str | None = None) -> Run | ScanJob:
        """Scan with the current profile and rig into ``out`` (default: the session's output
        directory), with the profile's calibration or the ``calibration`` file. Blocks and
        returns the :class:`Run`, or with ``wait=False`` returns a :class:`ScanJob` at once. A
        stopped scan returns normally with status ``aborted``."""
        with self._lock, self._state_lock:
            self._require_profile()
            self._require_idle("start a scan")
            self._stop = threading.Event()
            self._running = threading.Event()
            self._running.set()
            self._state = "running"
        target = lambda: self._run_scan(Path(out) if out is not None else self.out_dir,  # noqa: E731
                                        calibration)
        if wait:
            return target()
        self.job = ScanJob(target)
        return self.job

    def _run_scan(self, out: Path, calibration: Path | str | None = None) -> Run:
        from dotshell.pipeline.scan import scan

        self._live = {}
        try:
            result = scan(self.profile, self.pm, out, bus=self.bus, stop=self._stop,  # type: ignore[arg-type]
                          running=self._running, rig=self.rig,
                          calibration_file=str(calibration) if calibration else None)
        finally:  # a failed run is the session's last run too
            if self._live.get("run_dir"):
                self.run = Run(self._live["run_dir"])
            self._live = {"run_dir": self._live.get("run_dir")}  # no frame kept past the scan
            with self._state_lock:
                self._state = "idle"
            self._refresh_namespaces()
        run = self.run = Run(result.run_dir)
        products = run.root / RunLayout.CURRENT  # the published generation the report belongs to
        base = products.resolve() if products.is_symlink() else run.root
        for kind, rel in (result.report.get("previews") or {}).items():
            self.bus.emit(PreviewSaved(kind=kind, path=str(base / rel)))
        self._refresh_namespaces()
        return run

    def normalize(self, run: Run | str | Path | None = None,
                  normalizer: str | None = None) -> dict[str, Any]:
        """Normalize a run's trans-illumination frames on its surface (default: the session's
        last run) and return the report section (docs/transillumination.md)."""
        from dotshell.pipeline.commands import normalize_run

        target = run if run is not None else self.run
        if target is None:
            raise RunError("no run to normalize: scan first or give a run directory.")
        root = target.root if isinstance(target, Run) else Path(target)
        self._require_idle("normalize")
        return normalize_run(root, self.pm, self.bus, normalizer=normalizer)

    def _transition(self, allowed: tuple[str, ...], to: str) -> bool:
        """Move the scan state from one of ``allowed`` to ``to``; False if it was elsewhere."""
        with self._state_lock:
            if self._state not in allowed:
                return False
            self._state = to
            return True

    def pause(self) -> None:
        """Pause the running scan before its next frame."""
        if self._transition(("running",), "paused"):
            self._running.clear()
            self.bus.info("pause requested: the scan stops before its next frame")

    def resume(self) -> None:
        """Resume a paused scan."""
        if self._transition(("paused",), "running"):
            self._running.set()
            self.bus.info("resume requested")

    def abort(self) -> None:
        """Stop the scan cleanly: frames captured so far are kept, the run is ``aborted``. Never
        waits for a device action under way."""
        if self._transition(("running", "paused"), "stopping"):
            self._stop.set()
            self.bus.warn("abort requested: stopping the scan, frames are kept")

    def wait(self, timeout: float | None = None) -> Run:
        """Wait for a background scan (``scan(wait=False)``) and return its run."""
        if self.job is None:
            raise RunError("no background scan was started; use scan(wait=False) first.")
        return self.job.wait(timeout)

    def _live_preview(self, ev: Event) -> None:
        """During a scan, render the first frame of each captured view to
        ``<run>/live/latest_frame.png`` (capture-time, like the frames: ``<run>/previews``
        is the link to the current generation's previews, made when the products are
        published; a real folder there kept the link from ever being made)."""
        if isinstance(ev, ScanStarted):
            self._live = {"run_dir": ev.run_dir}
        elif isinstance(ev, ScanFinished):
            self._live["run_dir"] = ev.run_dir
        elif isinstance(ev, ViewCaptured) and self._live.get("run_dir"):
            from dotshell.render.previews import frame_preview
            from dotshell.run.store import RunStore

            store = RunStore(Path(self._live["run_dir"]))
            try:
                frame = store.frames(ev.view).read_one(0)
            except RunError:
                return
            store.path(RunLayout.LIVE).mkdir(exist_ok=True)
            path = frame_preview(frame, store.path(RunLayout.LATEST_FRAME))
            bits = getattr(self.rig.camera, "bit_depth", None) if self.rig else None
            self.bus.emit(PreviewSaved(kind="frame", path=str(path), view=ev.view,
                                       stats=frame_stats(frame, bits)))

    # ---- lifetime and scripting -----------------------------------------------------------------

    def close(self) -> None:
        """Abort a running scan (waiting for it) and close the rig."""
        self.abort()
        if self.job is not None:
            self.job.thread.join()
        if self.rig is not None and self.rig.connected and not self.scanning:
            self.rig.close()

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def namespace(self) -> dict[str, Any]:
        """A fresh namespace for scripts and the console, bound to this session: ``rig``,
        ``profile`` and ``run`` follow the session as it changes."""
        import numpy as np

        import dotshell

        ns: dict[str, Any] = {
            "session": self, "np": np, "dotshell": dotshell, "Run": Run,
            "load": self.load, "set": self.set, "configure": self.configure,
            "connect": self.connect,
            "disconnect": self.disconnect, "status": self.status, "move_to": self.move_to,
            "jog": self.jog, "home": self.home, "set_analyzer": self.set_analyzer,
            "set_exposure": self.set_exposure, "patterns": self.patterns,
            "project": self.project, "snap": self.snap, "decode": self.decode,
            "scan": self.scan, "pause": self.pause, "resume": self.resume,
            "abort": self.abort, "stop": self.stop, "wait": self.wait,
            "normalize": self.normalize,
            "run_script": lambda path, *args: run_script(path, self, [str(a) for a in args]),
            "log_level": self.log_level,
            # as in Python's own REPL and in dotshell script: code pasted from a script that
            # ends with ``if __name__ == "__main__": main()`` runs its main()
            "__name__": "__main__",
        }
        self._bind(ns)
        return ns

    def _bind(self, ns: dict[str, Any]) -> None:
        holder = _Namespace(ns)
        self._namespaces.append(weakref.ref(holder))
        ns["__session_binding__"] = holder  # lives as long as the namespace does
        self._refresh_namespaces()

    def _refresh_namespaces(self) -> None:
        alive = []
        for ref in self._namespaces:
            holder = ref()
            if holder is None:
                continue
            holder.ns.update(rig=self.rig, profile=self.profile, run=self.run)
            alive.append(ref)
        self._namespaces = alive


def readable_repr(value: Any) -> str:
    """How the console shows a value: the rig and a profile as a sentence (their classes have
    no repr of their own), anything else as ``repr``."""
    from dotshell.profile.loader import Profile
    from dotshell.rig.assembly import Rig

    if isinstance(value, Rig):
        devices = ", ".join(f"{role} {value.profile.required_role(role)['backend']}"
                            + ("" if role in value.connected else " (closed)")
                            for role in value.devices)
        return f"<Rig of {value.profile.name}: {devices or 'no devices'}>"
    if isinstance(value, Profile):
        return (f"<Profile {value.name} from {value.source}: {len(value.angles_deg())} views, "
                f"exposure {value.scan.exposure_ms:g} ms, "
                f"coding {value.required_role('coding')['backend']}>")
    return repr(value)



class _Namespace:
    """Weakly referenced handle on a bound namespace dict (dicts cannot be weakly referenced)."""

    def __init__(self, ns: dict[str, Any]) -> None:
        self.ns = ns


def split_script_args(rest: Sequence[str]) -> tuple[dict[str, Any], list[str]]:
    """Split what follows ``dotshell script FILE.py`` into dotshell's options (``--profile``,
    ``--set``, ``--out``) and the script's own arguments: everything after ``--``, and any
    word before it that is not one of those options."""
    import argparse

    rest = list(rest)
    cut = rest.index("--") if "--" in rest else len(rest)
    parser = argparse.ArgumentParser(prog="dotshell script", add_help=False)
    parser.add_argument("--profile")
    parser.add_argument("--set", action="append", default=[])
    parser.add_argument("--out")
    ns, unknown = parser.parse_known_args(rest[:cut])
    return vars(ns), unknown + rest[cut + 1:]


class ScriptResult:
    """What :func:`run_script` left: the script's global names as attributes (``.names`` the
    whole namespace), shown in the console as one line rather than the whole namespace."""

    def __init__(self, path: Path, names: dict[str, Any], given: set[str]) -> None:
        self.path = path
        self.names = names
        self.given = given  # the names the namespace had before the script ran

    def __getattr__(self, name: str) -> Any:
        names = self.__dict__.get("names") or {}  # (empty before __init__: copy, pickle)
        if name in names:
            return names[name]
        raise AttributeError(f"the script defined no {name!r}")

    def __repr__(self) -> str:
        own = [k for k, v in self.names.items() if not k.startswith("_")
               and k not in self.given and not isinstance(v, types.ModuleType)]
        return f"<script {self.path} ran: defined {', '.join(own) or 'nothing'}>"


def run_script(path: Path | str, session: Session, argv: Sequence[str] = ()) -> ScriptResult:
    """Run a Python file in a fresh namespace of the session (as ``__main__``, ``sys.argv`` =
    ``[path, *argv]`` while it runs, restored after); what ``dotshell script`` does, and, as
    ``run_script(path, *args)``, what the console offers. A ``SystemExit`` with code 0 or None
    (``sys.exit()`` after argparse's ``--help``) ends the script quietly."""
    path = Path(path).expanduser()
    try:
        source = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise DotshellError(f"cannot read script {path}: {exc.strerror or exc}. Give the path "
                            "of a Python file.") from None
    ns = session.namespace()
    ns.update(__name__="__main__", __file__=str(path))
    given = set(ns)
    old_argv = sys.argv
    sys.argv = [str(path), *argv]
    try:
        exec(compile(source, str(path), "exec"), ns)
    except SystemExit as exc:
        if exc.code not in (None, 0):
            raise
    except DotshellError:
        raise
    except Exception as exc:  # the script's own error: its traceback, not "a bug in dotshell"
        raise ScriptError(f"script {path} failed:\n{script_traceback(exc, path)}") from None
    finally:
        sys.argv = old_argv
    return ScriptResult(path, ns, given)


class ScriptError(DotshellError):
    """A user's script raised (or does not compile); the message holds its traceback."""

    exit_code = 1


def script_traceback(exc: BaseException, path: Path) -> str:
    """The traceback of ``exc`` from the script's first frame on (dotshell's frames that ran
    the script left out); for a syntax error, the line and the caret."""
    import traceback

    if isinstance(exc, SyntaxError):
        return "".join(traceback.format_exception_only(exc)).rstrip()
    tb = exc.__traceback__
    while tb is not None and tb.tb_frame.f_code.co_filename != str(path):
        tb = tb.tb_next
    return "".join(traceback.format_exception(type(exc), exc, tb)).rstrip()
