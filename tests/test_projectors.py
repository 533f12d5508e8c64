"""Projector drivers against their emulated far ends: the LightCrafter 4500 driver over pyusb on
the DLPC350 emulator (faults: NAK, wrong sequence, device gone, no reply, error registers,
rejected set-up), the framebuffer driver on file-backed framebuffers of every pixel layout."""

from __future__ import annotations

import numpy as np
import pytest

from dotshell.devices import SequencePattern
from dotshell.errors import DeviceError, DeviceLostError, DeviceTimeout
from dotshell.settings import validate_settings
from dotshell_projectors import dlpc350 as C
from dotshell_projectors import lc4500_images as images
from dotshell_projectors.framebuffer import SETTINGS_SCHEMA as FB_SCHEMA
from dotshell_projectors.framebuffer import FramebufferProjector, decode
from dotshell_projectors.lc4500_emulator import EmulatedLightCrafter
from dotshell_projectors.lightcrafter import SETTINGS_SCHEMA, LightCrafter4500

from test_hardware_scans import framebuffer_files


@pytest.fixture(scope="module")
def flash(tmp_path_factory):
    """30 random binary patterns packed into two flash images on disk."""
    rng = np.random.default_rng(0)
    patterns = [(rng.random((C.HEIGHT, C.WIDTH)) > 0.5).astype(np.uint8) * 255
                for _ in range(30)]
    paths = images.save(images.pack(patterns), tmp_path_factory.mktemp("flash"))
    return patterns, [str(p) for p in paths]


@pytest.fixture
def lc(flash):
    patterns, paths = flash
    emulator = EmulatedLightCrafter(images.load(paths), serial_number="LCR-42")
    dev = LightCrafter4500(validate_settings(SETTINGS_SCHEMA, {"flash_images": paths}, "lc"),
                           backend=emulator)
    dev.connect()
    yield dev, emulator, patterns
    dev.close()


def _sequence(patterns):
    return [SequencePattern(p, f"p{i}", i) for i, p in enumerate(patterns)]


def test_connect_reads_identity_from_usb_strings_and_version(lc):
    dev, emulator, _ = lc
    ident = dev.identity()
    assert (ident.serial_number, ident.firmware) == ("LCR-42", "4.4.0")
    assert dev.resolution == (912, 1140) and dev.status()["hardware_status"] == "0x01"
    decoded = dict(emulator.commands)
    assert decoded[C.DISP_MODE] == b"\x01" and decoded[C.PAT_DISP_MODE] == b"\x03"
    assert decoded[C.TRIG_OUT1_CTL] == bytes([0, 0xBB, 0xBB])  # active high, no delay


def test_sequence_displays_the_flash_bit_planes_in_order(lc):
    dev, emulator, patterns = lc
    period = dev.shortest_period_ms(20.0, 20.0)
    dev.load_sequence(_sequence(patterns), 20.0, period)
    dev.start_sequence()
    shown = emulator.displayed[-1]
    assert len(shown) == 30 and all(np.array_equal(a, b) for a, b in zip(shown, patterns))
    assert (emulator.state.exposure_us, emulator.state.period_us) == (20000, 20000)
    assert emulator.state.image_lut[:2] == [0, 1] and emulator.state.config[0] == 29
    # 30 entries × 3 bytes arrived through the pattern mailbox in 64-byte reports
    assert any(cmd == C.MBOX_DATA and len(p) == 90 for cmd, p in emulator.commands)
    dev.stop_sequence()
    dev.show(patterns[7], "p7", 7)
    assert np.array_equal(emulator.displayed[-1][0], patterns[7])
    assert dev.status()["pattern"] == "p7"


def test_period_rule_and_rejected_setup_name_the_validation_bit(lc):
    dev, emulator, patterns = lc
    assert dev.shortest_period_ms(20.0, 20.1) == pytest.approx(20.23)
    with pytest.raises(DeviceError, match="frame period minus exposure is less than 230"):
        dev.load_sequence(_sequence(patterns[:3]), 20.0, 20.1)


def test_unknown_pattern_names_the_fix(lc):
    dev, _, _ = lc
    with pytest.raises(DeviceError, match="lc4500_pack"):
        dev.show(np.full((C.HEIGHT, C.WIDTH), 128, np.uint8), "grey", 0)


@pytest.mark.parametrize("fault, error, text", [
    ("nak", DeviceError, "refused command 0x1a29 \\(NAK\\)"),
    ("wrong_sequence", DeviceError, "out of step"),
    ("gone", DeviceLostError, "gone from USB"),
    ("silent", DeviceTimeout, "no answer within 1000 ms"),
    ("hw_status", DeviceError, "0x41: bit 6: sequencer abort"),
])
def test_faults_become_named_device_errors(lc, fault, error, text):
    dev, emulator, patterns = lc
    if fault == "nak":
        emulator.nak = {C.PAT_EXPO_PRD}
    elif fault == "hw_status":
        emulator.hw_status = 0x41
    else:
        setattr(emulator, fault, True)
    with pytest.raises(error, match=text):
        dev.show(patterns[0], "p0", 0)


def test_lost_projector_reconnects(lc):
    dev, emulator, patterns = lc
    emulator.gone = True
    with pytest.raises(DeviceLostError):
        dev.show(patterns[0])
    emulator.gone = False
    dev.connect()
    dev.show(patterns[1])
    assert np.array_equal(emulator.displayed[-1][0], patterns[1])


def test_missing_projector_says_how_to_find_it(flash):
    emulator = EmulatedLightCrafter([])
    emulator.gone = True
    dev = LightCrafter4500(validate_settings(SETTINGS_SCHEMA, {"flash_images": flash[1]}, "lc"),
                           backend=emulator)
    with pytest.raises(DeviceError, match="0 devices 0451:6401.*udev"):
        dev.connect()


@pytest.mark.parametrize("bpp, layout", [(32, "xrgb8888"), (24, "bgr888"), (16, "rgb565"),
                                         (8, "gray8")])
def test_framebuffer_writes_every_layout_through_the_memory_map(tmp_path, bpp, layout):
    dev, sysfs = framebuffer_files(tmp_path, 40, 30, bpp)
    fb = FramebufferProjector(validate_settings(FB_SCHEMA, {
        "device": str(dev), "sysfs_dir": str(sysfs)}, "fb"))
    assert fb.resolution == (40, 30) and fb.geometry.layout == layout
    fb.connect()
    pattern = np.random.default_rng(1).integers(0, 256, (30, 40)).astype(np.uint8)
    fb.show(pattern, "noise", 3)
    fb.close()
    stride = int((sysfs / "stride").read_text())
    mem = np.fromfile(dev, np.uint8).reshape(-1, stride)[:30, :40 * bpp // 8]
    back = decode(mem.reshape(30, 40, bpp // 8), layout)
    tolerance = 8 if layout == "rgb565" else 0  # 5 bits for red and blue: steps of 8
    assert np.abs(back.astype(int) - pattern).max() <= tolerance


def test_framebuffer_geometry_errors_name_the_fix(tmp_path):
    dev, sysfs = framebuffer_files(tmp_path, 40, 30, 32)
    with pytest.raises(DeviceError, match="pixel_format 'rgb565' has 16 bits"):
        FramebufferProjector(validate_settings(FB_SCHEMA, {
            "device": str(dev), "sysfs_dir": str(sysfs), "pixel_format": "rgb565"}, "fb"))
    with pytest.raises(DeviceError, match="is the framebuffer driver loaded"):
        FramebufferProjector(validate_settings(FB_SCHEMA, {
            "device": str(dev), "sysfs_dir": str(tmp_path / "nowhere")}, "fb"))
    fb = FramebufferProjector(validate_settings(FB_SCHEMA, {
        "device": str(tmp_path / "fb9"), "sysfs_dir": str(sysfs)}, "fb"))
    with pytest.raises(DeviceError, match="ls /dev/fb"):
        fb.connect()


def test_the_lightcrafter_profile_flash_holds_its_coding(pm, tmp_path):
    from conftest import ROOT
    from dotshell.profile.loader import load_profile
    from dotshell_projectors.lc4500_pack import main

    profile = ROOT / "profiles" / "sim-metal-cylinder-lightcrafter.toml"
    prof = load_profile(profile, pm)
    coding = pm.create("coding", prof.role("coding")["backend"],
                       prof.role("coding")["settings"], None, prof.source)
    planes = images.Planes(images.load([ROOT / "profiles" / p for p in
                                        prof.role("projector")["settings"]["flash_images"]]))
    where = [planes.locate(p.image) for p in coding.patterns((C.WIDTH, C.HEIGHT))]
    assert len(where) == 44 and None not in where and where[0] == (0, 0)
    assert main([str(profile), str(tmp_path)]) == 0
    assert len(list(tmp_path.glob("lc4500_*.png"))) == 2
