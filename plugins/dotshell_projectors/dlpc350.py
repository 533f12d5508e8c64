"""The DLPC350 USB command set used by the LightCrafter 4500 driver and its emulator.

Facts from TI's *DLPC350 Programmer's Guide* (DLPU010G, 2018), section 1.2 (USB interface) and
chapter 2 (commands):

* The controller enumerates as a USB HID device, VID 0x0451, PID 0x6401, exchanging 64-byte
  reports on its interrupt endpoints (report ID 0, not sent on the wire).
* A message is a 4-byte header — flags (bit 7: 1 = read, 0 = write; bit 6: host wants a reply;
  bit 5: NAK, set by the controller when the command failed; bits 2:0: destination, 0 =
  projector control), a sequence byte the controller echoes, and the payload length (2 bytes,
  little-endian) — then the payload: the 16-bit command ``CMD2 << 8 | CMD3`` sent low byte
  first, then its parameters, little-endian. A payload longer than 60 bytes continues in
  further 64-byte reports without a header.
* A read request carries only the command; the controller answers with a header and the data.
* Pattern LUT entries are 24-bit words: bits 1:0 trigger type, 7:2 pattern number, 11:8 bit
  depth, 14:12 LED select, 16 invert, 17 insert black, 18 buffer swap, 19 trigger-out-1
  continues from the previous pattern. 1-bit pattern numbers 0–23 are the bit planes G0–G7,
  R0–R7, B0–B7 of a 24-bit flash image (Table 2-70).

This module holds the constants and the framing; the driver (:mod:`.lightcrafter`) and the
emulator (:mod:`.lc4500_emulator`) each build and parse messages on their own side.
"""

from __future__ import annotations

import struct

VENDOR_ID = 0x0451
PRODUCT_ID = 0x6401
REPORT_SIZE = 64
HEADER_SIZE = 4
ENDPOINT_OUT = 0x01
ENDPOINT_IN = 0x81

FLAG_READ = 0x80
FLAG_REPLY = 0x40
FLAG_NAK = 0x20

#: DLP4500 DMD as the DLPC350 addresses it in pattern mode: 912 columns × 1140 rows of diamond
#: pixels (rows at half the column pitch).
WIDTH, HEIGHT = 912, 1140

# Commands (CMD2 << 8 | CMD3) and their write parameter lengths in bytes.
POWER_CONTROL = 0x0200       # 1: 0 = normal, 1 = standby
GET_VERSION = 0x0205         # read 16: application, API, SW config, sequence config versions
STATUS_HW = 0x1A0A           # read 1: hardware status
STATUS_SYS = 0x1A0B          # read 1: system status
STATUS_MAIN = 0x1A0C         # read 1: main status
LED_ENABLE = 0x1A07          # 1: b3 sequencer controls the LEDs
LUT_VALID = 0x1A1A           # write 0 starts validation; read 1: b7 busy, b4:0 errors
DISP_MODE = 0x1A1B           # 1: 0 = video, 1 = pattern display
TRIG_OUT1_CTL = 0x1A1D       # 3: invert, rising delay, falling delay
PAT_DISP_MODE = 0x1A22       # 1: 0 = video port, 3 = flash
PAT_TRIG_MODE = 0x1A23       # 1: 1 = internal / external trigger
PAT_START_STOP = 0x1A24      # 1: 0 = stop, 1 = pause, 2 = start
PAT_EXPO_PRD = 0x1A29        # 8: exposure µs (u32), frame period µs (u32)
PAT_CONFIG = 0x1A31          # 4: LUT entries − 1, repeat, patterns for trigger out 2 − 1,
#                                 image LUT entries − 1
MBOX_ADDRESS = 0x1A32        # 1: offset in the open mailbox (0–127)
MBOX_CONTROL = 0x1A33        # 1: 0 = close, 1 = image LUT, 2 = pattern LUT
MBOX_DATA = 0x1A34           # n: LUT data

MBOX_CLOSED, MBOX_IMAGE_LUT, MBOX_PATTERN_LUT = 0, 1, 2
MAX_PATTERN_LUT = 128        # pattern LUT entries (mailbox offsets 0–127)
MAX_IMAGE_LUT = 64           # image index LUT entries
START, PAUSE, STOP = 2, 1, 0
TRIGGER_INTERNAL, TRIGGER_CONTINUE = 0, 3
LED_WHITE = 7
#: The frame period must equal the exposure or exceed it by at least this (µs).
MIN_DARK_US = 230
#: TRIG_OUT delay codes: 0xBB = 0 µs, each step 107.2 ns.
TRIGGER_DELAY_ZERO = 0xBB
TRIGGER_DELAY_STEP_US = 0.1072

#: Hardware status bits that are errors when set (bit 0, init done, is an error when clear).
HW_STATUS_ERRORS = {
    2: "DMD reset controller error: multiple overlapping bias or reset operations access the "
       "same DMD block",
    3: "forced swap error",
    6: "sequencer abort: the sequencer detected an error condition and aborted",
    7: "sequencer error",
}
HW_INIT_DONE = 0x01
SYS_MEMORY_TEST_PASSED = 0x01
MAIN_SEQUENCER_RUNNING = 0x02

#: LUT validation result bits (read of LUT_VALID once bit 7, busy, is clear).
VALIDATION_ERRORS = {
    0: "the exposure or frame period settings are invalid",
    1: "pattern numbers in the LUT are invalid",
    2: "continuous trigger out 1 request or overlapping black sectors",
    3: "post vector was not inserted before an externally triggered vector",
    4: "frame period minus exposure is less than 230 µs",
}
VALIDATION_BUSY = 0x80


def header(flags: int, seq: int, length: int) -> bytes:
    return struct.pack("<BBH", flags, seq & 0xFF, length)


def parse_header(report: bytes) -> tuple[int, int, int]:
    """(flags, sequence, payload length) of a report."""
    flags, seq, length = struct.unpack_from("<BBH", report)
    return flags, seq, length


def reports(flags: int, seq: int, payload: bytes) -> list[bytes]:
    """A message as 64-byte reports: header + first 60 payload bytes, then 64-byte chunks."""
    first = header(flags, seq, len(payload)) + payload[:REPORT_SIZE - HEADER_SIZE]
    out = [first]
    rest = payload[REPORT_SIZE - HEADER_SIZE:]
    out += [rest[i:i + REPORT_SIZE] for i in range(0, len(rest), REPORT_SIZE)]
    return [r.ljust(REPORT_SIZE, b"\0") for r in out]


def lut_word(pattern_number: int, bit_depth: int = 1, led: int = LED_WHITE,
             trigger: int = TRIGGER_INTERNAL, invert: bool = False, insert_black: bool = False,
             buffer_swap: bool = False, trigger_out_previous: bool = False) -> int:
    """One 24-bit pattern LUT entry (programmer's guide, Pattern Display LUT Data)."""
    return ((trigger & 0x3) | (pattern_number & 0x3F) << 2 | (bit_depth & 0xF) << 8
            | (led & 0x7) << 12 | int(invert) << 16 | int(insert_black) << 17
            | int(buffer_swap) << 18 | int(trigger_out_previous) << 19)


def plane_of(pattern_number: int) -> tuple[int, int]:
    """(RGB channel index, bit) of a 1-bit pattern number: 0–7 → G0–G7, 8–15 → R0–R7,
    16–23 → B0–B7."""
    channel = (1, 0, 2)[pattern_number // 8]
    return channel, pattern_number % 8
