"""Transcript tests of every tagger control request (exact setup packets, data and replies through
pyusb, every exchange consumed) and fuzzing of the reply decoders."""

from __future__ import annotations

import struct

import pytest
import usb.core
from hypothesis import given, settings
from hypothesis import strategies as st

from spdepth.drivers.errors import DeviceError, DeviceTimeoutError, ProtocolError, SettingError
from spdepth.drivers.sim.tagger_usb import TaggerUsbDescriptors
from spdepth.drivers.tagger import Tagger, TaggerSettings
from spdepth.drivers.tagger import protocol as proto
from spdepth.drivers.tagger.protocol import Gap, MarkerConfig, StatusFlag
from spdepth.drivers.tagger.transport import DeviceGoneError, EndpointStallError

IN, OUT = 0xC0, 0x40
IDENTITY = (b"SPDT" + struct.pack("<HBBHBBII", 1, 2, 5, 17, 4, 4, 1000, 2 ** 21)
            + b"UNIT42".ljust(12, b"\0"))


class TranscriptBackend(TaggerUsbDescriptors):
    """pyusb backend that plays a fixed list of control exchanges: each entry is
    ``(bmRequestType, bRequest, wValue, wIndex, wLength_or_out_data, reply_or_exception)``."""

    def __init__(self, exchanges):
        super().__init__()
        self.exchanges = list(exchanges)
        self.sent = []

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        assert self.exchanges, f"unexpected request {bRequest:#04x} after the transcript ended"
        rt, req, value, index, payload, reply = self.exchanges.pop(0)
        got = (bmRequestType, bRequest, wValue, wIndex,
               len(data) if bmRequestType & 0x80 else bytes(data))
        self.sent.append(got)
        assert got == (rt, req, value, index, payload)
        if isinstance(reply, Exception):
            raise reply
        if bmRequestType & 0x80:
            memoryview(data).cast("B")[:len(reply)] = reply
            return len(reply)
        return len(data)

    def assert_consumed(self):
        assert not self.exchanges, f"{len(self.exchanges)} exchanges never happened"


def opened(*exchanges):
    backend = TranscriptBackend([(IN, 0x01, 0, 0, 32, IDENTITY), *exchanges])
    return Tagger.open("usb:1209:7a64", backend=backend), backend


def test_identity_decoded_with_units():
    tagger, backend = opened()
    ident = tagger.identity
    assert ident.firmware == "2.5.17"
    assert ident.serial == "UNIT42"
    assert ident.base_resolution_s == pytest.approx(1e-12)
    assert (ident.n_channels, ident.n_marker_inputs, ident.fifo_capacity_records) == (4, 4, 2 ** 21)
    backend.assert_consumed()


def test_binning_request_and_readback():
    tagger, backend = opened((OUT, 0x10, 5, 0, b"", None),
                             (IN, 0x11, 0, 0, 8, struct.pack("<HHI", 5, 0, 32000)))
    b = tagger.set_binning(5)
    assert b.code == 5 and b.resolution_s == pytest.approx(32e-12)
    backend.assert_consumed()


def test_sync_divider_request_and_readback():
    tagger, backend = opened((OUT, 0x12, 8, 0, b"", None), (IN, 0x13, 0, 0, 2, b"\x08\x00"))
    tagger.set_sync_divider(8)
    backend.assert_consumed()


def test_marker_request_puts_enables_in_wvalue_and_edges_in_windex():
    tagger, backend = opened((OUT, 0x14, 0b1011, 0b0001, b"", None),
                             (IN, 0x15, 0, 0, 4, b"\x0b\x00\x01\x00"))
    tagger.set_markers(0b1011, 0b0001)
    backend.assert_consumed()


def test_start_stop_status_ack_gap():
    status = struct.pack("<IIIIQ", 0b011, 1234, 77, 50, 9000)
    gap = struct.pack("<QQI", 9000, 123456789, 50)
    tagger, backend = opened((OUT, 0x20, 0, 0, b"", None), (IN, 0x30, 0, 0, 24, status),
                             (IN, 0x31, 0, 0, 20, gap), (OUT, 0x21, 0, 0, b"", None))
    tagger.start()
    s = tagger.status()
    assert s.flags == StatusFlag.RUNNING | StatusFlag.OVERRUN and s.running and s.overrun
    assert (s.fifo_fill_records, s.lost_records, s.gap_lost_records, s.gap_position) == (1234, 77, 50, 9000)
    assert tagger.ack_gap() == Gap(9000, 123456789, 50)
    tagger.stop()
    backend.assert_consumed()


def test_configure_sends_all_settings_in_order():
    tagger, backend = opened(
        (OUT, 0x10, 3, 0, b"", None), (IN, 0x11, 0, 0, 8, struct.pack("<HHI", 3, 0, 8000)),
        (OUT, 0x12, 2, 0, b"", None), (IN, 0x13, 0, 0, 2, b"\x02\x00"),
        (OUT, 0x14, 0b1111, 0b0101, b"", None), (IN, 0x15, 0, 0, 4, b"\x0f\x00\x05\x00"))
    tagger.configure(TaggerSettings(binning=3, sync_divider=2, marker_rising_mask=0b0101))
    assert tagger.settings.sync_divider == 2
    backend.assert_consumed()


def test_readback_mismatch_is_a_device_error():
    tagger, backend = opened((OUT, 0x12, 4, 0, b"", None), (IN, 0x13, 0, 0, 2, b"\x01\x00"))
    with pytest.raises(DeviceError, match="kept sync divider 1"):
        tagger.set_sync_divider(4)
    backend.assert_consumed()


@pytest.mark.parametrize("exc,err", [
    (usb.core.USBError("Pipe error", -9, 32), EndpointStallError),
    (usb.core.USBError("No such device", -4, 19), DeviceGoneError),
    (usb.core.USBTimeoutError("Operation timed out", -7, 110), DeviceTimeoutError),
    (usb.core.USBError("I/O error", -1, 5), DeviceError),
])
def test_usb_errors_become_typed_errors(exc, err):
    tagger, backend = opened((IN, 0x30, 0, 0, 24, exc))
    with pytest.raises(err):
        tagger.status()
    backend.assert_consumed()


@pytest.mark.parametrize("call", [lambda t: t.set_binning(16), lambda t: t.set_sync_divider(3),
                                  lambda t: t.set_markers(0x10, 0), lambda t: t.set_markers(1, -1)])
def test_bad_settings_are_refused_before_anything_is_sent(call):
    tagger, backend = opened()
    with pytest.raises(SettingError):
        call(tagger)
    backend.assert_consumed()


def test_short_and_garbled_replies_are_protocol_errors():
    tagger, backend = opened((IN, 0x30, 0, 0, 24, b"\x01" * 10),
                             (IN, 0x30, 0, 0, 24, struct.pack("<IIIIQ", 0x80, 0, 0, 0, 0)),
                             (IN, 0x30, 0, 0, 24, struct.pack("<IIIIQ", 0x1, 0, 0, 5, 100)))
    with pytest.raises(ProtocolError, match="10 bytes"):
        tagger.status()
    with pytest.raises(ProtocolError, match="undefined flag"):
        tagger.status()
    with pytest.raises(ProtocolError, match="without the OVERRUN"):
        tagger.status()
    backend.assert_consumed()


def test_wrong_magic_is_refused():
    backend = TranscriptBackend([(IN, 0x01, 0, 0, 32, b"XXXX" + IDENTITY[4:])])
    with pytest.raises(ProtocolError, match="SPDT"):
        Tagger.open("usb:1209:7a64", backend=backend)


@pytest.mark.parametrize("url", ["usb:1209", "serial:1209:7a64", "usb:xyz:7a64", "usb:1209:10000"])
def test_bad_urls(url):
    with pytest.raises(SettingError):
        proto.parse_url(url)


def test_missing_device_is_device_gone():
    class Empty(TranscriptBackend):
        def enumerate_devices(self):
            return iter(())
    with pytest.raises(DeviceGoneError, match="1209:7a64"):
        Tagger.open("usb:1209:7a64", backend=Empty([]))


def test_encode_decode_replies_round_trip():
    ident = proto.decode_identity(IDENTITY)
    assert proto.encode_identity(ident) == IDENTITY
    assert proto.decode_markers(proto.encode_markers(MarkerConfig(5, 1))) == MarkerConfig(5, 1)
    g = Gap(1, 2 ** 40, 7)
    assert proto.decode_gap(proto.encode_gap(g)) == g


DECODERS = [proto.decode_identity, proto.decode_binning, proto.decode_sync_divider,
            proto.decode_markers, proto.decode_status, proto.decode_gap]


@settings(max_examples=150, deadline=None)
@given(st.sampled_from(DECODERS), st.binary(max_size=40))
def test_fuzz_reply_decoders_return_or_raise_protocol_error(decoder, data):
    try:
        decoder(data)
    except ProtocolError:
        pass


@settings(max_examples=150, deadline=None)
@given(st.sampled_from([(proto.decode_identity, IDENTITY),
                        (proto.decode_status, struct.pack("<IIIIQ", 3, 1, 2, 3, 4)),
                        (proto.decode_gap, struct.pack("<QQI", 1, 2, 3))]),
       st.integers(0, 40))
def test_fuzz_truncated_replies_raise(pair, cut):
    decoder, good = pair
    decoder(good)
    if cut < len(good):
        with pytest.raises(ProtocolError):
            decoder(good[:cut])
