"""An emulated LightCrafter 4500 as a pyusb backend: ``usb.core.find(backend=EmulatedLightCrafter(...))``.

The far end of the real driver (:mod:`dotshell_projectors.lightcrafter`): it enumerates as
0451:6401 with one HID interface (interrupt endpoints 0x01 out, 0x81 in, 64-byte reports) and
USB string descriptors, reassembles the DLPC350 messages from the 64-byte reports, decodes the
commands the driver uses (see :mod:`dotshell_projectors.dlpc350`) into controller state, answers
reads and acknowledges writes with the host's sequence byte, validates the pattern set-up the
way the programmer's guide describes (period = exposure or ≥ exposure + 230 µs, 1-bit pattern
numbers 0–23, images present) and, on start, displays the bit planes of its flash images through
a ``display`` (the simulator's projector optics, :mod:`dotshell_projectors.simulated`).

Fault switches for tests: ``nak`` (command codes answered with the NAK flag), ``wrong_sequence``
(replies carry another sequence byte), ``gone`` (the device vanished: transfers fail with
ENODEV and it no longer enumerates), ``silent`` (no replies: reads time out) and ``hw_status``
(the hardware status register, e.g. 0x41 = sequencer abort).

Behaviour the guide leaves open and the emulator chooses: a start without a valid validation
since the last set-up change sets the sequencer-abort bit (0x40) of the hardware status and
displays nothing; a set-up command while a sequence runs is NAKed.
"""

from __future__ import annotations

import array
import errno
import struct
import time
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Protocol, Sequence

import numpy as np
import usb.backend
import usb.core

from dotshell_projectors import dlpc350 as C

MANUFACTURER = "Texas Instruments"
PRODUCT = "DLPC350"


class Display(Protocol):
    """Where the emulated DMD's light goes (times on the display's own clock)."""

    def now(self) -> float: ...

    def run(self, images: list[np.ndarray], exposure_s: float, period_s: float) -> None: ...

    def show(self, image: np.ndarray) -> None: ...

    def stop(self) -> None: ...


@dataclass
class Controller:
    """DLPC350 state the commands set."""

    power_standby: int = 0
    display_mode: int = 0
    pattern_source: int = 3
    trigger_mode: int = 1
    led_enable: int = 0x08
    trig_out1: bytes = bytes([0, C.TRIGGER_DELAY_ZERO, C.TRIGGER_DELAY_ZERO])
    exposure_us: int = 0
    period_us: int = 0
    config: bytes = bytes(4)
    mailbox: int = C.MBOX_CLOSED
    mailbox_address: int = 0
    image_lut: list[int] = field(default_factory=lambda: [0] * C.MAX_IMAGE_LUT)
    pattern_lut: list[int] = field(default_factory=lambda: [0] * C.MAX_PATTERN_LUT)
    validation: int | None = None   # None = not validated since the last change
    busy_reads: int = 0             # LUT_VALID reads still answered "busy"
    running_until: float = -1.0     # display clock time the sequence ends (inf = repeating)


class EmulatedLightCrafter(usb.backend.IBackend):
    """A pyusb backend with one emulated LightCrafter 4500 on it."""

    def __init__(self, flash_images: Sequence[np.ndarray], serial_number: str = "EMU4500-0001",
                 display: Display | None = None, firmware: tuple[int, int, int] = (4, 4, 0)):
        super().__init__()
        self.flash = [np.asarray(i, np.uint8) for i in flash_images]
        self.serial_number = serial_number
        self.display = display
        self.firmware = firmware
        self.state = Controller()
        self.hw_status = C.HW_INIT_DONE
        self.sys_status = C.SYS_MEMORY_TEST_PASSED
        self.nak: set[int] = set()
        self.wrong_sequence = False
        self.gone = False
        self.silent = False
        self.commands: list[tuple[int, bytes]] = []   # decoded (command, params), in order
        self.displayed: list[list[np.ndarray]] = []   # image lists shown on start
        self._partial: tuple[int, int, bytearray, int] | None = None
        self._replies: list[bytes] = []
        self._device = SimpleNamespace(bus=1, address=7)

    # ---- descriptors -------------------------------------------------------------------------

    def enumerate_devices(self):
        return [] if self.gone else [self._device]

    def get_device_descriptor(self, dev):
        return SimpleNamespace(
            bLength=18, bDescriptorType=1, bcdUSB=0x0200, bDeviceClass=0, bDeviceSubClass=0,
            bDeviceProtocol=0, bMaxPacketSize0=64, idVendor=C.VENDOR_ID, idProduct=C.PRODUCT_ID,
            bcdDevice=0x0100, iManufacturer=1, iProduct=2, iSerialNumber=3,
            bNumConfigurations=1, address=dev.address, bus=dev.bus, port_number=1,
            port_numbers=(1,), speed=2)

    def get_configuration_descriptor(self, dev, config):
        return SimpleNamespace(bLength=9, bDescriptorType=2, wTotalLength=41, bNumInterfaces=1,
                               bConfigurationValue=1, iConfiguration=0, bmAttributes=0x80,
                               bMaxPower=50, extra_descriptors=[])

    def get_interface_descriptor(self, dev, intf, alt, config):
        return SimpleNamespace(bLength=9, bDescriptorType=4, bInterfaceNumber=0,
                               bAlternateSetting=0, bNumEndpoints=2, bInterfaceClass=3,
                               bInterfaceSubClass=0, bInterfaceProtocol=0, iInterface=0,
                               extra_descriptors=[])

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        address = (C.ENDPOINT_IN, C.ENDPOINT_OUT)[ep]
        return SimpleNamespace(bLength=7, bDescriptorType=5, bEndpointAddress=address,
                               bmAttributes=3, wMaxPacketSize=C.REPORT_SIZE, bInterval=1,
                               bRefresh=0, bSynchAddress=0, extra_descriptors=[])

    # ---- handles -----------------------------------------------------------------------------

    def _alive(self) -> None:
        if self.gone:
            raise usb.core.USBError("No such device (it may have been disconnected)",
                                    error_code=-4, errno=errno.ENODEV)

    def open_device(self, dev):
        self._alive()
        return self._device

    def close_device(self, dev_handle):
        pass

    def set_configuration(self, dev_handle, config_value):
        self._alive()

    def get_configuration(self, dev_handle):
        return 1

    def claim_interface(self, dev_handle, intf):
        self._alive()

    def release_interface(self, dev_handle, intf):
        pass

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def detach_kernel_driver(self, dev_handle, intf):
        pass

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        """GET_DESCRIPTOR of string descriptors (language list, manufacturer, product,
        serial number); anything else stalls."""
        self._alive()
        if bmRequestType == 0x80 and bRequest == 6 and wValue >> 8 == 3:
            index = wValue & 0xFF
            if index == 0:
                body = struct.pack("<H", 0x0409)
            else:
                text = {1: MANUFACTURER, 2: PRODUCT, 3: self.serial_number}.get(index)
                if text is None:
                    raise usb.core.USBError("Pipe error", error_code=-9, errno=errno.EPIPE)
                body = text.encode("utf-16-le")
            desc = bytes([2 + len(body), 3]) + body
            n = min(len(desc), len(data))
            data[:n] = array.array("B", desc[:n])
            return n
        raise usb.core.USBError("Pipe error", error_code=-9, errno=errno.EPIPE)

    # ---- HID reports -------------------------------------------------------------------------

    def intr_write(self, dev_handle, ep, intf, data, timeout):
        self._alive()
        report = bytes(data)
        if len(report) != C.REPORT_SIZE:
            raise usb.core.USBError(f"report of {len(report)} bytes (the DLPC350 takes 64)",
                                    error_code=-1, errno=errno.EIO)
        if self._partial is None:
            flags, seq, length = struct.unpack_from("<BBH", report)
            body = bytearray(report[C.HEADER_SIZE:C.HEADER_SIZE + length])
            self._partial = (flags, seq, body, length)
        else:
            flags, seq, body, length = self._partial
            body += report[:length - len(body)]
        flags, seq, body, length = self._partial
        if len(body) >= length:
            self._partial = None
            self._message(flags, seq, bytes(body))
        return len(report)

    def intr_read(self, dev_handle, ep, intf, buff, timeout):
        self._alive()
        if not self._replies:
            raise usb.core.USBTimeoutError("Operation timed out", error_code=-7,
                                           errno=errno.ETIMEDOUT)
        report = self._replies.pop(0)
        n = min(len(buff), len(report))
        buff[:n] = array.array("B", report[:n])
        return n

    def _reply(self, flags: int, seq: int, data: bytes = b"") -> None:
        if self.silent:
            return
        seq = (seq + 1) & 0xFF if self.wrong_sequence else seq
        self._replies += C.reports(flags, seq, data)

    # ---- commands ----------------------------------------------------------------------------

    def _message(self, flags: int, seq: int, payload: bytes) -> None:
        command = payload[0] | payload[1] << 8
        params = payload[2:]
        self.commands.append((command, params))
        wants_reply = bool(flags & C.FLAG_REPLY)
        if command in self.nak:
            self._reply(C.FLAG_NAK, seq)
            return
        try:
            if flags & C.FLAG_READ:
                self._reply(C.FLAG_READ, seq, self._read(command))
                return
            self._write(command, params)
        except _Refused:
            self._reply(C.FLAG_NAK, seq)
            return
        if wants_reply:
            self._reply(0, seq)

    def _read(self, command: int) -> bytes:
        s = self.state
        if command == C.GET_VERSION:
            major, minor, patch = self.firmware
            return struct.pack("<IIII", major << 24 | minor << 16 | patch, 0, 0, 0)
        if command == C.STATUS_HW:
            return bytes([self.hw_status])
        if command == C.STATUS_SYS:
            return bytes([self.sys_status])
        if command == C.STATUS_MAIN:
            return bytes([C.MAIN_SEQUENCER_RUNNING if self._running() else 0])
        if command == C.LUT_VALID:
            if s.busy_reads > 0:
                s.busy_reads -= 1
                return bytes([C.VALIDATION_BUSY])
            return bytes([0 if s.validation is None else s.validation])
        simple = {C.POWER_CONTROL: s.power_standby, C.DISP_MODE: s.display_mode,
                  C.PAT_DISP_MODE: s.pattern_source, C.PAT_TRIG_MODE: s.trigger_mode,
                  C.LED_ENABLE: s.led_enable}
        if command in simple:
            return bytes([simple[command]])
        if command == C.PAT_EXPO_PRD:
            return struct.pack("<II", s.exposure_us, s.period_us)
        if command == C.PAT_CONFIG:
            return s.config
        if command == C.TRIG_OUT1_CTL:
            return s.trig_out1
        raise _Refused

    def _write(self, command: int, p: bytes) -> None:
        s = self.state
        setup = {C.DISP_MODE, C.PAT_DISP_MODE, C.PAT_TRIG_MODE, C.PAT_EXPO_PRD, C.PAT_CONFIG,
                 C.MBOX_CONTROL, C.MBOX_ADDRESS, C.MBOX_DATA, C.TRIG_OUT1_CTL, C.LUT_VALID}
        if command in setup and self._running():
            raise _Refused  # stop the sequence before changing the set-up
        if command in setup - {C.LUT_VALID}:
            s.validation = None
        if command == C.POWER_CONTROL:
            s.power_standby = _u8(p)
        elif command == C.DISP_MODE:
            s.display_mode = _u8(p)
        elif command == C.PAT_DISP_MODE:
            s.pattern_source = _u8(p)
        elif command == C.PAT_TRIG_MODE:
            s.trigger_mode = _u8(p)
        elif command == C.LED_ENABLE:
            s.led_enable = _u8(p)
        elif command == C.TRIG_OUT1_CTL:
            s.trig_out1 = _exact(p, 3)
        elif command == C.PAT_EXPO_PRD:
            s.exposure_us, s.period_us = struct.unpack("<II", _exact(p, 8))
        elif command == C.PAT_CONFIG:
            s.config = _exact(p, 4)
        elif command == C.MBOX_CONTROL:
            s.mailbox = _u8(p)
            s.mailbox_address = 0
        elif command == C.MBOX_ADDRESS:
            s.mailbox_address = _u8(p)
        elif command == C.MBOX_DATA:
            self._mailbox_data(p)
        elif command == C.LUT_VALID:
            s.validation = self._validate()
            s.busy_reads = 1
        elif command == C.PAT_START_STOP:
            self._start_stop(_u8(p))
        else:
            raise _Refused

    def _mailbox_data(self, p: bytes) -> None:
        s = self.state
        if s.mailbox == C.MBOX_IMAGE_LUT:
            entries, size = list(p), 1
        elif s.mailbox == C.MBOX_PATTERN_LUT:
            if len(p) % 3:
                raise _Refused
            entries = [int.from_bytes(p[i:i + 3], "little") for i in range(0, len(p), 3)]
            size = 3
        else:
            raise _Refused  # no mailbox open
        lut = s.image_lut if size == 1 else s.pattern_lut
        if s.mailbox_address + len(entries) > len(lut):
            raise _Refused
        lut[s.mailbox_address:s.mailbox_address + len(entries)] = entries

    def _validate(self) -> int:
        s = self.state
        bits = 0
        if s.exposure_us <= 0 or s.exposure_us > s.period_us:
            bits |= 1 << 0
        elif 0 < s.period_us - s.exposure_us < C.MIN_DARK_US:
            bits |= 1 << 4
        n_lut, _, _, n_images = (v + 1 for v in s.config)
        for word in s.pattern_lut[:n_lut]:
            number, depth = word >> 2 & 0x3F, word >> 8 & 0xF
            if depth != 1 or number > 23:
                bits |= 1 << 1
        if any(i >= len(self.flash) for i in s.image_lut[:n_images]):
            bits |= 1 << 1
        if not s.pattern_lut[0] >> 18 & 1:  # the first pattern must load an image
            bits |= 1 << 1
        return bits

    def _planes(self) -> list[np.ndarray]:
        s = self.state
        n_lut, _, _, n_images = (v + 1 for v in s.config)
        out, pos = [], -1
        for word in s.pattern_lut[:n_lut]:
            if word >> 18 & 1:
                pos = min(pos + 1, n_images - 1)
            image = self.flash[s.image_lut[pos]]
            channel, bit = C.plane_of(word >> 2 & 0x3F)
            plane = ((image[..., channel] >> bit) & 1).astype(np.uint8) * np.uint8(255)
            if word >> 16 & 1:
                plane = 255 - plane
            if word >> 12 & 0x7 == 0:  # no LED lit
                plane = np.zeros_like(plane)
            out.append(plane)
        return out

    def _start_stop(self, action: int) -> None:
        s = self.state
        if action == C.STOP or action == C.PAUSE:
            if self.display is not None and self._running():
                self.display.stop()
            s.running_until = -1.0
            return
        if action != C.START:
            raise _Refused
        if s.validation is None or s.validation & 0x03:
            self.hw_status |= 0x40  # sequencer abort: an unvalidated or invalid set-up
            return
        images = self._planes()
        self.displayed.append(images)
        repeat = bool(s.config[1])
        now = self._now()
        if self.display is not None:
            if repeat and len(images) == 1:
                self.display.show(images[0])
            else:
                self.display.run(images * (100 if repeat else 1), s.exposure_us / 1e6,
                                 s.period_us / 1e6)
        s.running_until = float("inf") if repeat else now + len(images) * s.period_us / 1e6

    def _now(self) -> float:
        return self.display.now() if self.display is not None else time.monotonic()

    def _running(self) -> bool:
        return self._now() < self.state.running_until


class _Refused(Exception):
    """A command the emulated controller answers with NAK."""


def _u8(p: bytes) -> int:
    return _exact(p, 1)[0]


def _exact(p: bytes, n: int) -> bytes:
    if len(p) != n:
        raise _Refused
    return p
