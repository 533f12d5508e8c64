"""Exception types. Every :class:`DotshellError` is an expected, user-fixable failure: front
ends print its message (one paragraph naming the thing and the fix) and exit with code 2."""


class DotshellError(Exception):
    """Base of all expected failures; the message is shown to the user as is."""

    exit_code = 2


class ProfileError(DotshellError):
    """A profile file is missing, unreadable or invalid."""


class PluginError(DotshellError):
    """A plugin failed to load, or a requested backend does not exist."""


class CalibrationError(DotshellError):
    """A calibration is missing, malformed or unusable."""


class DeviceError(DotshellError):
    """A device failed to connect or to perform a step.

    Raised by backends for a recoverable per-step failure (a dropped frame, a timeout); the
    acquisition runner retries the step before giving up.
    """


class RunError(DotshellError):
    """A run directory is missing pieces or cannot be processed."""


class ReconstructionError(DotshellError):
    """Processing produced nothing usable (no decoded pixels, empty cloud, ...)."""


class DeviceLostError(DeviceError):
    """The device is gone (unplugged, port vanished, powered off). The rig reconnects it once
    (``reconnect = true``, the default) before the step fails."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its timeout; recoverable like any DeviceError."""


class DeviceStopped(DeviceError):
    """A device call ended because :meth:`dotshell.rig.assembly.Rig.stop` stopped the device (abort,
    Ctrl-C, SIGTERM, SIGHUP). Never retried; the runner ends the scan as ``aborted``."""


class PluginFault(DotshellError):
    """Plugin code raised something other than a :class:`DotshellError`; the message names the
    plugin, role, backend and what was being done."""


class FrameError(DotshellError):
    """A frame (from the camera or from a run's files) is not what the run's frames are: its
    size, dtype, bit depth or channels differ (see :mod:`dotshell.run.framecheck`)."""


class Interrupted(KeyboardInterrupt):
    """The process was asked to stop (Ctrl-C, SIGTERM, SIGHUP): ``signame`` says which. Not a
    :class:`DotshellError`: a stop is obeyed, not reported (raised by
    :func:`dotshell.run.lifecycle.interrupts`)."""

    def __init__(self, signame: str = "SIGINT") -> None:
        super().__init__(signame)
        self.signame = signame

    @property
    def reason(self) -> str:
        what = {"SIGINT": "Ctrl-C (SIGINT)", "SIGTERM": "SIGTERM", "SIGHUP":
                "SIGHUP (the terminal or SSH session closed)"}.get(self.signame, self.signame)
        return f"stopped by {what}"
