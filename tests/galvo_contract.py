"""Contract checks every galvo controller must pass: the emulator over the URL handler, the
emulator over a pty, and a real controller (tests/hil). Each takes a connected ``Galvo``.

They leave the controller reset (``*RST``) and only move the mirror inside its soft limits."""

from __future__ import annotations

import pytest

from spdepth.drivers.galvo import (BadArgumentError, BusyError, ErrorCode, Galvo, GalvoState, Gate,
                           GateMode, OutOfRangeError, PatternCodes, PixelFlag, ScanMode,
                           UnknownCommandError)
from tests.waiting import wait_until


def _fresh(g: Galvo) -> None:
    g.reset()
    while g.next_error()[0] != ErrorCode.NO_ERROR:
        pass
    g.limits()


def check_identity(g: Galvo) -> None:
    ident = g.identify()
    assert ident == g.identify()
    assert all(ident.__dict__.values())
    cal = g.calibration()
    assert cal.x_udeg_per_code > 0 and 0 <= cal.x_zero_code <= 65535


def check_move_round_trip(g: Galvo) -> None:
    _fresh(g)
    g.move_codes(30000, 35000)
    assert g.position_codes() == (30000, 35000)
    assert g.status().state == GalvoState.IDLE
    g.move_deg(1.5, -2.25)
    x, y = g.position_deg()
    per_code = g.calibration().x_udeg_per_code * 1e-6
    assert abs(x - 1.5) <= per_code and abs(y + 2.25) <= per_code
    g.set_park_position_codes(32000, 33000)
    g.park()
    assert g.position_codes() == (32000, 33000)
    assert g.status().state == GalvoState.PARKED


def check_error_replies(g: Galvo) -> None:
    """The controller's own checks (bypassing the driver's) give each numbered error and queue it."""
    _fresh(g)
    cases = [(UnknownCommandError, ("FROB",)), (BadArgumentError, ("POS", 1)),
             (BadArgumentError, ("GATE", "SOMETIMES", 5)), (OutOfRangeError, ("POS", 70000, 0)),
             (OutOfRangeError, ("PAT", "RASTER", 0, 4, 0, 10, 0, 10))]
    for cls, (mnemonic, *args) in cases:
        with pytest.raises(cls) as exc:
            g._query(mnemonic, *args)
        assert exc.value.message
    codes = [g.next_error()[0] for _ in cases]
    assert codes == [ErrorCode.UNKNOWN_COMMAND, ErrorCode.BAD_ARGUMENT, ErrorCode.BAD_ARGUMENT,
                     ErrorCode.OUT_OF_RANGE, ErrorCode.OUT_OF_RANGE]
    assert g.next_error() == (ErrorCode.NO_ERROR, "no error")


def check_settings_read_back(g: Galvo) -> None:
    _fresh(g)
    p = PatternCodes(ScanMode.SERPENTINE, 5, 3, 30000, 31000, 32000, 32500)
    g.configure_scan(p, Gate.count(7, 2e-3), settle_s=1e-6, frames=2)
    assert g.pattern() == p
    gate = g.gate()
    assert (gate.mode, gate.n_target, gate.dwell_ns) == (GateMode.COUNT, 7, 2_000_000)
    assert g.settle_s() == pytest.approx(1e-6)
    assert g.frames() == 2


def _all_pixels(g: Galvo, timeout_s: float = 20.0):
    g.wait_until_done(timeout_s)
    recs = []
    while True:
        page = g.poll_pixels()
        assert page.lost == 0
        if not page.records:
            return recs
        recs += page.records


def check_fixed_dwell_raster(g: Galvo, mode: ScanMode = ScanMode.RASTER) -> None:
    _fresh(g)
    g.configure_scan(PatternCodes(mode, 4, 3, 30000, 33000, 31000, 34000), Gate.fixed(20e-6))
    before = g.start()
    recs = _all_pixels(g)
    st = g.status()
    assert st.state == GalvoState.PARKED and st.scan_id == before.scan_id + 1
    assert st.completed == st.total == 12
    order = [(r.row, r.col) for r in recs]
    expect = [(row, col) for row in range(3)
              for col in (range(3, -1, -1) if mode == ScanMode.SERPENTINE and row % 2 else range(4))]
    assert order == expect
    assert [r.seq for r in recs] == list(range(12))
    assert all(r.flag == PixelFlag.FIXED and r.dwell_ns == pytest.approx(20_000, rel=0.01)
               for r in recs)
    assert g.position_codes() == g.park_position_codes()


def check_count_gated(g: Galvo, n_target: int = 5) -> None:
    _fresh(g)
    g.configure_scan(PatternCodes(ScanMode.RASTER, 3, 2, 30000, 33000, 31000, 34000),
                     Gate.count(n_target, 1e-3))
    g.start()
    recs = _all_pixels(g)
    assert len(recs) == 6
    for r in recs:
        if r.flag == PixelFlag.GATED:
            assert r.count >= n_target and r.dwell_ns <= 1_000_000
        else:
            assert r.flag == PixelFlag.LIMIT
            assert r.count < n_target and r.dwell_ns == pytest.approx(1_000_000, rel=1e-3)


def check_busy_and_stop(g: Galvo) -> None:
    _fresh(g)
    # 64 x 0.2 s: a starved test thread still catches it running; STOP ends it after one pixel
    g.configure_scan(PatternCodes(ScanMode.RASTER, 8, 8, 30000, 33000, 31000, 34000),
                     Gate.fixed(0.2))
    g.start()
    st = g.status()
    assert st.state == GalvoState.SCANNING and st.total == 64
    with pytest.raises(BusyError):
        g.move_codes(30000, 30000)
    with pytest.raises(BusyError):
        g.set_frames(3)
    with pytest.raises(BusyError):
        g._query("START")
    wait_until(lambda: g.status().completed > 0, 10.0, poll_s=0.01, what="a first pixel")
    g.stop()
    st = g.status()
    assert st.state == GalvoState.PARKED and 0 < st.completed < 64
    assert len(_all_pixels(g)) == st.completed
    g.stop()                                  # STOP when idle is a harmless OK


CONTRACT = [check_identity, check_move_round_trip, check_error_replies, check_settings_read_back,
            check_fixed_dwell_raster, check_count_gated, check_busy_and_stop]
