"""Texas Instruments DLP LightCrafter 4500 (DLPC350 controller) over USB HID with pyusb.

The projector runs in *pattern display mode* from its flash: the coding's binary patterns are
bit planes of 24-bit images stored in the projector's flash (see
:mod:`dotshell_projectors.lc4500_images`). ``load_sequence`` finds each pattern's image and bit
plane, writes the image index LUT and the pattern LUT through the DLPC350 mailboxes, sets the
pattern exposure and frame period, TRIG_OUT_1 (to the camera's trigger input) and validates the
whole set-up with the controller (its validation bits become a named error). ``start_sequence``
runs it once on the projector's internal trigger: every pattern gets a TRIG_OUT_1 pulse for its
exposure. ``show`` displays one stored pattern, repeated, for the show/settle/capture path.

The hardware status register is read after every start and in ``status()``: an error bit
(sequencer abort, DMD reset controller error, ...) is raised as a DeviceError naming it.

Command set and framing: TI *DLPC350 Programmer's Guide* (DLPU010G), see
:mod:`dotshell_projectors.dlpc350`.
"""

from __future__ import annotations

import errno
import struct
import time
from typing import Any, Sequence

import numpy as np

from dotshell.devices import DeviceIdentity, SequencePattern
from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.settings import Setting
from dotshell_projectors import dlpc350 as C
from dotshell_projectors.lc4500_images import Planes, load

NAME = "LightCrafter 4500"

SETTINGS_SCHEMA: dict[str, Setting] = {
    "flash_images": Setting("list[str]", [], "the 24-bit images stored in the projector's "
                            "flash, in flash order (relative to the profile); written by python "
                            "-m dotshell_projectors.lc4500_pack"),
    "serial_number": Setting("str", "", "USB serial number of the projector to open; empty = "
                             "the only one connected"),
    "led": Setting("str", "white", "LEDs lit for the patterns",
                   choices=("red", "green", "blue", "white")),
    "trigger_invert": Setting("bool", False, "TRIG_OUT_1 active low (for cameras triggering on "
                              "a falling edge)"),
    "trigger_delay_us": Setting("float", 0.0, "TRIG_OUT_1 rising-edge delay relative to the "
                                "pattern (−20.05 to +2.78 µs, 107.2 ns steps)", "µs",
                                min=-20.05, max=2.787),
    "show_period_ms": Setting("float", 16.667, "frame period of a pattern shown with show() "
                              "(repeated until the next one)", "ms", min=1.0),
    "usb_timeout_ms": Setting("int", 1000, "timeout of one USB transfer", "ms", min=10),
    "validate_timeout_ms": Setting("int", 2000, "how long to wait for the controller to "
                                   "validate a LUT", "ms", min=100),
}

_LEDS = {"red": 1, "green": 2, "blue": 4, "white": 7}


def _bits_named(value: int, names: dict[int, str]) -> list[str]:
    return [f"bit {b}: {text}" for b, text in names.items() if value >> b & 1]


class LightCrafter4500:
    """Projector, SequencedProjector and Identified over the DLPC350 USB HID protocol.

    ``backend`` is a pyusb backend (None = libusb, found through ``libusb-package``); tests pass
    the emulator's (:class:`dotshell_projectors.lc4500_emulator.EmulatedLightCrafter`)."""

    def __init__(self, settings: dict[str, Any], base_dir: str = ".",
                 backend: Any = None) -> None:
        self.settings = settings
        self.base_dir = base_dir
        self.backend = backend
        self.dev: Any = None
        self.seq = 0
        self.planes: Planes | None = None
        self.firmware = ""
        self.serial = ""
        self.loaded: list[SequencePattern] = []
        self.last_shown: tuple[str, int] = ("", -1)
        self.hw_status: int | None = None

    # ---- Device ------------------------------------------------------------------------------

    @property
    def resolution(self) -> tuple[int, int]:
        return (C.WIDTH, C.HEIGHT)

    def connect(self) -> None:
        import usb.core

        from pathlib import Path

        paths = [p if Path(p).is_absolute() else str(Path(self.base_dir) / p)
                 for p in self.settings["flash_images"]]
        if not paths:
            raise DeviceError(f"{NAME}: [projector.settings] flash_images is empty; list the "
                              "24-bit images stored in the projector's flash (docs/hardware.md).")
        self.planes = Planes(load(paths))
        backend = self.backend if self.backend is not None else _libusb_backend()
        found = list(usb.core.find(find_all=True, idVendor=C.VENDOR_ID, idProduct=C.PRODUCT_ID,
                                   backend=backend))
        want = self.settings["serial_number"]
        if want:
            found = [d for d in found if _serial(d) == want]
        if len(found) != 1:
            which = f" with serial number {want!r}" if want else ""
            raise DeviceError(
                f"{NAME}: {len(found)} devices {C.VENDOR_ID:04x}:{C.PRODUCT_ID:04x}{which} on "
                "USB. Is it powered and plugged in (lsusb lists it)? On Linux give your user "
                "access with a udev rule for 0451:6401; with several, set serial_number.")
        self.dev = found[0]
        try:
            if self.dev.is_kernel_driver_active(0):  # usbhid claims it on Linux
                self.dev.detach_kernel_driver(0)
        except (NotImplementedError, usb.core.USBError):
            pass
        self._usb(self.dev.set_configuration, "configure the USB device")
        self.serial = _serial(self.dev)
        app = struct.unpack_from("<I", self.read(C.GET_VERSION, 16))[0]
        self.firmware = f"{app >> 24}.{app >> 16 & 0xFF}.{app & 0xFFFF}"
        if self.read(C.POWER_CONTROL, 1)[0] != 0:
            self.write(C.POWER_CONTROL, b"\x00")  # leave standby
        self.check_status()
        self.write(C.PAT_START_STOP, bytes([C.STOP]))
        self.write(C.DISP_MODE, b"\x01")           # pattern display mode
        self.write(C.PAT_DISP_MODE, b"\x03")       # patterns from flash
        self.write(C.PAT_TRIG_MODE, b"\x01")       # internal trigger
        self.write(C.LED_ENABLE, b"\x08")          # LEDs switched by the sequencer
        delay = round(C.TRIGGER_DELAY_ZERO + self.settings["trigger_delay_us"]
                      / C.TRIGGER_DELAY_STEP_US)
        self.write(C.TRIG_OUT1_CTL, bytes([int(self.settings["trigger_invert"]), delay, delay]))

    def close(self) -> None:
        if self.dev is None:
            return
        import usb.util

        try:
            self.write(C.PAT_START_STOP, bytes([C.STOP]))
        except DeviceError:
            pass
        try:
            usb.util.dispose_resources(self.dev)
        except Exception:  # closing must not raise
            pass
        self.dev = None
        self.loaded = []

    def identity(self) -> DeviceIdentity:
        return DeviceIdentity(model="DLP LightCrafter 4500 (DLPC350)", serial_number=self.serial,
                              firmware=self.firmware, vendor="Texas Instruments")

    def status(self) -> dict[str, Any]:
        name, index = self.last_shown
        out: dict[str, Any] = {"connected": self.dev is not None, "pattern": name,
                               "pattern_index": index, "sequence_patterns": len(self.loaded),
                               "firmware": self.firmware}
        if self.hw_status is not None:
            out["hardware_status"] = f"0x{self.hw_status:02x}"
        return out

    # ---- Projector ---------------------------------------------------------------------------

    def show(self, pattern: np.ndarray, name: str = "", index: int = -1) -> None:
        """Display a pattern stored in flash, repeated until the next call."""
        where = self._locate(pattern, name or f"index {index}")
        period_us = round(self.settings["show_period_ms"] * 1000)
        self._program([where], period_us, period_us, repeat=True)
        self.write(C.PAT_START_STOP, bytes([C.START]))
        self.check_status()
        self.last_shown = (name, index)
        self.loaded = []

    # ---- SequencedProjector ------------------------------------------------------------------

    def shortest_period_ms(self, exposure_ms: float, at_least_ms: float) -> float:
        """The period equals the exposure or exceeds it by 230 µs (programmer's guide)."""
        exposure_us = round(exposure_ms * 1000)
        want_us = max(exposure_us, round(at_least_ms * 1000 + 0.4999))
        if want_us > exposure_us:
            want_us = max(want_us, exposure_us + C.MIN_DARK_US)
        return want_us / 1000.0

    def load_sequence(self, patterns: Sequence[SequencePattern], exposure_ms: float,
                      period_ms: float) -> None:
        if len(patterns) > C.MAX_PATTERN_LUT:
            raise DeviceError(f"{NAME}: a sequence holds at most {C.MAX_PATTERN_LUT} patterns, "
                              f"got {len(patterns)}.")
        where = [self._locate(p.image, p.name or f"index {p.index}") for p in patterns]
        self._program(where, round(exposure_ms * 1000), round(period_ms * 1000), repeat=False)
        self.loaded = list(patterns)

    def start_sequence(self) -> None:
        if not self.loaded:
            raise DeviceError(f"{NAME}: start_sequence() before load_sequence(); load the "
                              "patterns first.")
        self.write(C.PAT_START_STOP, bytes([C.START]))
        self.check_status()

    def stop_sequence(self) -> None:
        if self.dev is not None:
            self.write(C.PAT_START_STOP, bytes([C.STOP]))

    # ---- set-up ------------------------------------------------------------------------------

    def _locate(self, pattern: np.ndarray, what: str) -> tuple[int, int]:
        if self.dev is None or self.planes is None:
            raise DeviceError(f"{NAME}: not connected; connect the rig first.")
        where = self.planes.locate(pattern)
        if where is None:
            raise DeviceError(
                f"{NAME}: pattern {what} is not among the {24 * self.planes.count} bit planes "
                "of flash_images; the projector displays only patterns stored in its flash. "
                "Write this coding's images with python -m dotshell_projectors.lc4500_pack, "
                "put them in the projector's flash with TI's LightCrafter 4500 GUI and list them "
                "in flash_images.")
        return where

    def _program(self, where: list[tuple[int, int]], exposure_us: int, period_us: int,
                 repeat: bool) -> None:
        """Stop, write both LUTs, exposure/period and the LUT configuration, validate."""
        images: list[int] = []
        words = []
        for image, number in where:
            swap = not images or images[-1] != image
            if swap:
                images.append(image)
            words.append(C.lut_word(number, led=_LEDS[self.settings["led"]], buffer_swap=swap))
        if len(images) > C.MAX_IMAGE_LUT:
            raise DeviceError(f"{NAME}: the sequence changes flash image {len(images)} times; "
                              f"the image LUT holds {C.MAX_IMAGE_LUT}. Store the patterns in "
                              "sequence order.")
        self.write(C.PAT_START_STOP, bytes([C.STOP]))
        self.write(C.PAT_CONFIG, bytes([len(words) - 1, int(repeat), len(words) - 1,
                                        len(images) - 1]))
        self.write(C.PAT_EXPO_PRD, struct.pack("<II", exposure_us, period_us))
        self._mailbox(C.MBOX_IMAGE_LUT, bytes(images))
        self._mailbox(C.MBOX_PATTERN_LUT, b"".join(struct.pack("<I", w)[:3] for w in words))
        self._validate()

    def _mailbox(self, which: int, data: bytes) -> None:
        self.write(C.MBOX_CONTROL, bytes([which]))
        self.write(C.MBOX_ADDRESS, b"\x00")
        self.write(C.MBOX_DATA, data)
        self.write(C.MBOX_CONTROL, bytes([C.MBOX_CLOSED]))

    def _validate(self) -> None:
        self.write(C.LUT_VALID, b"")
        deadline = time.monotonic() + self.settings["validate_timeout_ms"] / 1000.0
        while True:
            result = self.read(C.LUT_VALID, 1)[0]
            if not result & C.VALIDATION_BUSY:
                break
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"{NAME}: the controller did not finish validating the "
                                    "pattern LUT in time.")
            time.sleep(0.01)
        errors = _bits_named(result, C.VALIDATION_ERRORS)
        if errors:
            raise DeviceError(f"{NAME}: the controller rejected the pattern set-up (validation "
                              f"0x{result:02x}): {'; '.join(errors)}.")

    def check_status(self) -> None:
        """Read the hardware, system and main status registers; a DeviceError names every
        error bit set."""
        hw = self.hw_status = self.read(C.STATUS_HW, 1)[0]
        sys_ = self.read(C.STATUS_SYS, 1)[0]
        errors = _bits_named(hw, C.HW_STATUS_ERRORS)
        if not hw & C.HW_INIT_DONE:
            errors.insert(0, "bit 0: internal initialization failed")
        if not sys_ & C.SYS_MEMORY_TEST_PASSED:
            errors.append(f"system status 0x{sys_:02x}: internal memory test failed")
        if errors:
            raise DeviceError(f"{NAME}: hardware status 0x{hw:02x}: {'; '.join(errors)}. "
                              "Power-cycle the projector; if it persists, check the pattern "
                              "set-up (exposure, period, LUT) in docs/hardware.md.")

    # ---- USB HID transport -------------------------------------------------------------------

    def write(self, command: int, params: bytes) -> None:
        """A write command with an acknowledgement; a NAK is a DeviceError."""
        self._transact(C.FLAG_REPLY, command, params)

    def read(self, command: int, size: int) -> bytes:
        """A read command; returns at least ``size`` data bytes."""
        data = self._transact(C.FLAG_READ | C.FLAG_REPLY, command, b"")
        if len(data) < size:
            raise DeviceError(f"{NAME}: command 0x{command:04x} answered {len(data)} bytes, "
                              f"expected {size}.")
        return data

    def _transact(self, flags: int, command: int, params: bytes) -> bytes:
        if self.dev is None:
            raise DeviceError(f"{NAME}: not connected; connect the rig first.")
        self.seq = (self.seq + 1) & 0xFF
        payload = struct.pack("<H", command) + params
        timeout = self.settings["usb_timeout_ms"]
        for report in C.reports(flags, self.seq, payload):
            self._usb(lambda r=report: self.dev.write(C.ENDPOINT_OUT, r, timeout),
                      f"send command 0x{command:04x}")
        first = bytes(self._usb(lambda: self.dev.read(C.ENDPOINT_IN, C.REPORT_SIZE, timeout),
                                f"read the reply to command 0x{command:04x}"))
        rflags, rseq, length = C.parse_header(first)
        if rseq != self.seq:
            raise DeviceError(f"{NAME}: reply to command 0x{command:04x} carries sequence "
                              f"{rseq}, expected {self.seq}: replies are out of step (another "
                              "program using the projector?).")
        if rflags & C.FLAG_NAK:
            raise DeviceError(f"{NAME}: the controller refused command 0x{command:04x} "
                              f"(NAK){_hint(command)}.")
        data = first[C.HEADER_SIZE:C.HEADER_SIZE + length]
        while len(data) < length:
            more = bytes(self._usb(lambda: self.dev.read(C.ENDPOINT_IN, C.REPORT_SIZE, timeout),
                                   f"read the reply to command 0x{command:04x}"))
            data += more[:length - len(data)]
        return data

    def _usb(self, action, what: str):
        import usb.core

        try:
            return action()
        except usb.core.USBTimeoutError:
            raise DeviceTimeout(f"{NAME}: no answer within {self.settings['usb_timeout_ms']} ms "
                                f"to {what}.") from None
        except usb.core.USBError as exc:
            if exc.errno in (errno.ENODEV, errno.EIO, errno.EPIPE) or "No such device" in str(exc):
                self.dev = None
                raise DeviceLostError(f"{NAME}: the projector is gone from USB ({exc}) while "
                                      f"trying to {what}; check the cable and power.") from None
            if exc.errno == errno.EACCES:
                raise DeviceError(f"{NAME}: no permission to open the USB device ({exc}); add "
                                  "a udev rule for 0451:6401 (docs/hardware.md).") from None
            raise DeviceError(f"{NAME}: USB error while trying to {what}: {exc}") from None


def _hint(command: int) -> str:
    if command in (C.PAT_CONFIG, C.PAT_EXPO_PRD, C.MBOX_DATA, C.MBOX_CONTROL, C.MBOX_ADDRESS):
        return "; stop the running sequence before changing the pattern set-up"
    return ""


def _serial(dev: Any) -> str:
    try:
        return dev.serial_number or ""
    except Exception:  # no string descriptor or no permission to read it
        return ""


def _libusb_backend() -> Any:
    import usb.backend.libusb1

    try:
        import libusb_package

        backend = usb.backend.libusb1.get_backend(
            find_library=lambda _: libusb_package.get_library_path())
    except ImportError:
        backend = usb.backend.libusb1.get_backend()
    if backend is None:
        raise DeviceError(f"{NAME}: no libusb found; pip install libusb-package (a dependency "
                          "of dotshell) or install libusb-1.0.")
    return backend
