"""Fuzz of every input kind beyond PTUs: first-photon-imaging .mat files, a session's ``run.json`` and
``events.jsonl``, the window's settings file. Each is damaged (bytes flipped), truncated, given
wrong types and huge values, deterministically (seeded), and read the way a user reaches it (the
CLI in this process, the window constructed over the settings file). Every input must end in at
most three lines on stderr and no traceback: no exception escapes ``main`` (it turns only the
errors spdepth raises on purpose into one line; anything else is a bug with its traceback) and
nothing is logged with one.

Each test prints its counts, inputs tried and the exit statuses seen (``pytest -n 0 -s``: in the
suite's two processes pytest-xdist does not show what a test prints)."""

from __future__ import annotations

import collections
import json
import logging
import shutil
import warnings

import numpy as np
import pytest
import scipy.io

from spdepth.acq.cli import main

HUGE = (1e308, -1e308, 2**63, -(2**63), 10**30, float("nan"), float("inf"))
WRONG = (None, "x", [], {}, [1, 2], True, -1, 0, 1e308, "1e999", {"a": {"b": [None]}})


def _run(argv, capsys, caplog) -> tuple[int, list[str]]:
    """``spdepth ARGV`` in this process: its exit status and stderr lines; fails on an exception
    that escapes (a traceback) or a log record carrying one."""
    caplog.clear()
    with caplog.at_level(logging.WARNING), warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        # Python does not show these to a user (its default filters ignore them)
        warnings.simplefilter("ignore", ResourceWarning)
        try:
            code = main(argv)
        except BaseException as exc:  # noqa: BLE001 - the point: nothing may escape
            raise AssertionError(f"spdepth {' '.join(argv)}: {type(exc).__name__}: {exc}") from exc
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    # Python prints a warning as two lines on stderr ("file:line: RuntimeWarning: ...", the code)
    assert not warned, f"spdepth {' '.join(argv)}: {warned[0].category.__name__}: {warned[0].message}"
    traced = [r for r in caplog.records if r.exc_info]
    assert not traced, f"spdepth {' '.join(argv)}: logged a traceback: {traced[0].getMessage()}"
    assert not any("Traceback" in ln for ln in err), err
    logged = [ln for r in caplog.records for ln in r.getMessage().splitlines()]
    return code, err + logged


class Tally:
    """Inputs tried per kind and the statuses seen; failures collected, reported together."""

    def __init__(self, kind: str):
        self.kind = kind
        self.codes = collections.Counter()
        self.failures: list[str] = []

    def check(self, what: str, argv, capsys, caplog, lines_max: int = 3) -> None:
        try:
            code, lines = _run(argv, capsys, caplog)
            self.codes[code] += 1
            if code not in (0, 1, 2, 3):
                self.failures.append(f"{what}: exit {code}")
            elif code != 0 and not lines:
                self.failures.append(f"{what}: exit {code} with nothing said")
            elif len(lines) > lines_max:
                self.failures.append(f"{what}: {len(lines)} lines: {lines[:5]}")
        except AssertionError as exc:
            self.codes["traceback"] += 1
            self.failures.append(f"{what}: {exc}")

    def done(self) -> None:
        n = sum(self.codes.values())
        print(f"\nfuzz {self.kind}: {n} inputs, exit statuses {dict(sorted(self.codes.items(), key=str))}, "
              f"tracebacks {self.codes['traceback']}")
        assert not self.failures, f"{len(self.failures)} of {n}:\n" + "\n".join(self.failures[:30])


def _mutations(data: bytes, rng, n_cuts: int, n_flips: int):
    """(name, bytes): cuts at spread positions and at the ends, then runs of flipped bytes."""
    size = len(data)
    cuts = sorted(set([0, 1, 8, 127, 128, 129, size - 1, size - 2]
                      + [int(x) for x in rng.integers(1, size, n_cuts)]))
    for c in cuts:
        if 0 <= c < size:
            yield f"cut at {c}", data[:c]
    for i in range(n_flips):
        b = bytearray(data)
        at = int(rng.integers(0, size))
        k = int(rng.integers(1, 9))
        b[at:at + k] = rng.integers(0, 256, k, dtype=np.uint8).tobytes()
        yield f"flip {k} at {at}", bytes(b)


# ---------------------------------------------------------------------------------- .mat files

def _cells(items, shape):
    out = np.empty(shape, dtype=object)
    for i, v in enumerate(items):
        out.flat[i] = v
    return out


def _good_cells(rng):
    items = [rng.normal(3000, 40, int(rng.integers(0, 12)))[:, None] for _ in range(20)]
    return _cells(items, (4, 5))


def _mat_variants(tmp, rng):
    """(name, path) of broken .mat files: byte damage of two good files (compressed and not),
    and well-formed files holding the wrong things."""
    good = {"plain": tmp / "good_plain.mat", "zipped": tmp / "good_zip.mat"}
    scipy.io.savemat(good["plain"], {"Ts": _good_cells(rng)}, do_compression=False)
    scipy.io.savemat(good["zipped"], {"Ts": _good_cells(rng)}, do_compression=True)
    for label, path in good.items():
        yield f"{label} as written", path
        for name, data in _mutations(path.read_bytes(), rng, 30, 40):
            p = tmp / f"m{rng.integers(1 << 30)}.mat"
            p.write_bytes(data)
            yield f"{label} {name}", p
    content = {
        "a string in a cell": _cells(["hello"] + [np.ones((1, 1))] * 5, (2, 3)),
        "a struct in a cell": _cells([{"a": 1}] + [np.ones((1, 1))] * 5, (2, 3)),
        "a matrix in a cell": _cells([np.ones((3, 3))] + [np.ones((1, 1))] * 5, (2, 3)),
        "complex times": _cells([np.array([[1 + 2j]])] * 6, (2, 3)),
        "NaN times": _cells([np.array([[np.nan, 1.0]])] * 6, (2, 3)),
        "infinite times": _cells([np.array([[np.inf]])] * 6, (2, 3)),
        "huge times": _cells([np.array([[1e300, 2e300]])] * 6, (2, 3)),
        "huge and small times": _cells([np.array([[0.0, 1e15]])] * 6, (2, 3)),
        "negative times": _cells([np.array([[-5.0, -1.0, 3.0]])] * 6, (2, 3)),
        "int8 times": _cells([np.array([[1, 2, 3]], np.int8)] * 6, (2, 3)),
        "uint64 huge times": _cells([np.array([[2**63]], np.uint64)] * 6, (2, 3)),
        "bool times": _cells([np.array([[True, False]])] * 6, (2, 3)),
        "nested cells": _cells([_cells([np.ones((1, 1))], (1, 1))] * 6, (2, 3)),
        "all cells empty": _cells([np.zeros((0, 0))] * 6, (2, 3)),
        "one time in all": _cells([np.array([[7.0]])] * 6, (2, 3)),
        "a 1x1 image": _cells([np.array([[1.0, 2.0, 3.0]])], (1, 1)),
        "a 1x2000 image": _cells([np.array([[float(i)]]) for i in range(2000)], (1, 2000)),
    }
    for name, cells in content.items():
        p = tmp / f"c{rng.integers(1 << 30)}.mat"
        scipy.io.savemat(p, {"Ts": cells})
        yield name, p
    for name, mdict in {"no cell array": {"x": np.ones(3)}, "two cell arrays": {
            "a": _good_cells(rng), "b": _good_cells(rng)}, "an empty cell array": {
            "Ts": np.empty((0, 0), dtype=object)}, "a 3-D cell array": {
            "Ts": _cells([np.ones((1, 1))] * 8, (2, 2, 2))}, "nothing": {}}.items():
        p = tmp / f"v{rng.integers(1 << 30)}.mat"
        scipy.io.savemat(p, mdict)
        yield name, p


@pytest.mark.slow
def test_fuzz_mat_files(tmp_path, rng, capsys, caplog):
    tally = Tally(".mat")
    for name, path in _mat_variants(tmp_path, rng):
        tally.check(name, ["recon", str(path), "--time-unit-ps", "8", "--pulse-rms-ps", "360"],
                    capsys, caplog)
    # and without a pulse: the estimate of the pulse from damaged data must fail in one line too
    for name, path in list(_mat_variants(tmp_path / "again", rng))[::7]:
        tally.check(name + " (pulse estimated)", ["recon", str(path), "--time-unit-ps", "8"],
                    capsys, caplog)
    tally.done()


@pytest.fixture(autouse=True)
def _again_folder(tmp_path):
    (tmp_path / "again").mkdir()


# ------------------------------------------------------------------- a session's files

@pytest.fixture(scope="module")
def session_dir(tmp_path_factory):
    """A small simulated session with a lost span (two passes): recording, events, run.json."""
    out = tmp_path_factory.mktemp("fuzz_session") / "run"
    assert main(["scan", "--sim", "--size", "10x8", "--target", "6", "--faults",
                 "fifo-overflow@40%", "--out", str(out)]) == 0
    return out


def _session_copy(session_dir, tmp, i) -> object:
    d = tmp / f"s{i}"
    shutil.copytree(session_dir, d)
    return d


def _json_variants(doc: dict, rng):
    """(name, text) of a JSON document made wrong: each top-level field, and each field one level
    down, given wrong types and huge values or removed; the whole document not an object."""
    yield "not an object (list)", json.dumps([doc])
    yield "not an object (number)", "1e999"
    yield "null", "null"
    yield "empty", ""
    for key, value in doc.items():
        yield f"{key} removed", json.dumps({k: v for k, v in doc.items() if k != key})
        for bad in rng.choice(np.array(WRONG + HUGE, dtype=object), 3, replace=False):
            yield f"{key} = {bad!r}", json.dumps({**doc, key: bad})
        if isinstance(value, dict):
            for sub in list(value)[:12]:
                bad = rng.choice(np.array(WRONG + HUGE, dtype=object))
                yield f"{key}.{sub} = {bad!r}", json.dumps({**doc, key: {**value, sub: bad}})


@pytest.mark.slow
def test_fuzz_run_json(session_dir, tmp_path, rng, capsys, caplog):
    tally = Tally("run.json")
    text = (session_dir / "run.json").read_text()
    variants = list(_json_variants(json.loads(text), rng))
    variants += [(name, data.decode("utf-8", "replace"))
                 for name, data in _mutations(text.encode(), rng, 10, 10)]
    for i, (name, body) in enumerate(variants):
        d = _session_copy(session_dir, tmp_path, i)
        (d / "run.json").write_text(body)
        tally.check(name, ["recon", str(d / "recording.ptu"), "--npz", str(tmp_path / f"r{i}.npz")],
                    capsys, caplog)
        shutil.rmtree(d)
    tally.done()


def _event_variants(lines: list[str], rng):
    """(name, text) of an event log made wrong: cut, lines dropped or doubled, lines of the wrong
    JSON type, each event's fields given wrong types and huge values."""
    text = "".join(lines)
    for name, data in _mutations(text.encode(), rng, 10, 10):
        yield name, data.decode("utf-8", "replace")
    yield "empty", ""
    for i, line in enumerate(lines):
        yield f"line {i + 1} dropped", "".join(lines[:i] + lines[i + 1:])
        yield f"line {i + 1} twice", "".join(lines[:i + 1] + lines[i:])
        for bad in ("[1, 2]\n", "3\n", '"x"\n', "null\n", "{}\n", "\n"):
            yield f"line {i + 1} is {bad.strip() or 'blank'}", "".join(lines[:i] + [bad] + lines[i + 1:])
        e = json.loads(line)
        if e.get("event") in ("session", "pixels"):
            continue               # what replay reads: pass, pass_end, lost, state
        for key in e:
            if key == "event":
                continue
            for bad in rng.choice(np.array(WRONG + HUGE, dtype=object), 3, replace=False):
                yield (f"line {i + 1} ({e['event']}) {key} = {bad!r}",
                       "".join(lines[:i] + [json.dumps({**e, key: bad}) + "\n"] + lines[i + 1:]))
            if isinstance(e[key], dict):
                for sub in e[key]:
                    bad = rng.choice(np.array(WRONG + HUGE, dtype=object))
                    yield (f"line {i + 1} ({e['event']}) {key}.{sub} = {bad!r}",
                           "".join(lines[:i] + [json.dumps({**e, key: {**e[key], sub: bad}}) + "\n"]
                                   + lines[i + 1:]))


#: test_fuzz_events_jsonl runs in this many parts, so that the suite's two processes share it
#: (each part about 15 s)
EVENT_PARTS = 3


@pytest.mark.slow
@pytest.mark.parametrize("part", range(EVENT_PARTS))
def test_fuzz_events_jsonl(part, session_dir, tmp_path, capsys, caplog):
    tally = Tally(f"events.jsonl, part {part + 1} of {EVENT_PARTS}")
    lines = (session_dir / "events.jsonl").read_text().splitlines(keepends=True)
    assert any('"event": "lost"' in ln for ln in lines)
    # a third of the variants, drawn by one seeded rng for every part (not the per-test rng fixture,
    # seeded by each part's own name), each part replaying every EVENT_PARTS-th of them: each is a
    # whole replay (about 0.4 s)
    rng = np.random.default_rng(0x5EED_E7E5)
    variants = list(_event_variants(lines, rng))
    keep = np.sort(rng.choice(len(variants), len(variants) // 3, replace=False))
    mine = range(part, keep.size, EVENT_PARTS)
    for i in mine:
        name, body = variants[keep[i]]
        d = _session_copy(session_dir, tmp_path, i)
        (d / "events.jsonl").write_text(body)
        tally.check(name + " (replay)", ["replay", str(d), "--out", str(tmp_path / f"o{i}")],
                    capsys, caplog)
        if i % 3 == 0:
            tally.check(name + " (recon)", ["recon", str(d / "recording.ptu")], capsys, caplog)
        shutil.rmtree(d)
        shutil.rmtree(tmp_path / f"o{i}", ignore_errors=True)
    print(f"\nfuzz events.jsonl, part {part + 1} of {EVENT_PARTS}: {len(mine)} "
          f"of {len(keep)} damaged logs (of {len(variants)} made), each replayed and every third also "
          f"reconstructed")
    tally.done()


# ---------------------------------------------------------------- the window's settings file

@pytest.mark.slow
def test_fuzz_window_settings(tmp_path, rng, qtbot, caplog):
    pytest.importorskip("pytestqt")
    from PySide6 import QtCore

    from spdepth.gui.app import remembered
    from spdepth.gui.sources import SETTINGS_KEY, Remembered, SourceSpec
    from spdepth.gui.window import MainWindow

    spec = SourceSpec(kind="sim", out_root=str(tmp_path / "runs"))
    good = json.loads(Remembered().store(spec))
    variants = [(f"{SETTINGS_KEY}: {name}", {SETTINGS_KEY: body})
                for name, body in _json_variants(good, rng)]
    legacy = spec.to_dict()             # the single "source" dict of earlier versions
    variants += [(f"source (legacy): {name}", {"source": body})
                 for name, body in list(_json_variants(legacy, rng))[::3]]
    variants += [("geometry garbage", {"geometry": QtCore.QByteArray(b"\x00\x01garbage")}),
                 ("splitter garbage", {"splitter": QtCore.QByteArray(b"\xff" * 40)}),
                 ("geometry a string", {"geometry": "not bytes"}),
                 ("splitter a number", {"splitter": 12}),
                 ("last_save a list", {"last_save": [1, 2]})]
    ini = tmp_path / "good.ini"
    s = QtCore.QSettings(str(ini), QtCore.QSettings.IniFormat)
    s.setValue(SETTINGS_KEY, json.dumps(good))
    s.sync()
    for name, data in _mutations(ini.read_bytes(), rng, 15, 25):
        variants.append((f"file {name}", data))
    tally = Tally("window settings")
    # one window, its settings read again from each file (a window costs about a second to make);
    # the first few files get a window of their own, as at start-up
    shared = MainWindow(settings=QtCore.QSettings(str(ini), QtCore.QSettings.IniFormat))
    qtbot.addWidget(shared)
    for i, (name, content) in enumerate(variants):
        path = tmp_path / f"w{i}.ini"
        if isinstance(content, bytes):
            path.write_bytes(content)
        else:
            s = QtCore.QSettings(str(path), QtCore.QSettings.IniFormat)
            for k, v in content.items():
                s.setValue(k, v)
            s.sync()
        caplog.clear()
        try:
            with caplog.at_level(logging.WARNING):
                settings = QtCore.QSettings(str(path), QtCore.QSettings.IniFormat)
                remembered(settings)
                if i < 5:
                    w = MainWindow(settings=settings)
                    qtbot.addWidget(w)
                else:
                    w = shared
                    w.settings = settings
                    w._restore_settings()
                w.controls.spec().to_dict()
            lines = [ln for r in caplog.records for ln in r.getMessage().splitlines()]
            traced = [r for r in caplog.records if r.exc_info]
            if traced or len(lines) > 3:
                tally.failures.append(f"{name}: {lines[:4]}")
                tally.codes["traceback" if traced else "too many lines"] += 1
            else:
                tally.codes["opened"] += 1
        except Exception as exc:  # noqa: BLE001 - the point: a bad settings file must not stop the window
            tally.codes["traceback"] += 1
            tally.failures.append(f"{name}: {type(exc).__name__}: {exc}")
    tally.done()


# ---------------------------------------------------------------------------- histogram cubes

def _cube_files(tmp, rng):
    """(name, path) of count cubes (H x W x T) in .npy, .npz and .mat: written well and damaged
    byte by byte, and holding the wrong things (negative, fractional, NaN, huge counts, too few
    or too many dimensions, no time bins, text, complex numbers)."""
    good = rng.poisson(0.3, (6, 5, 64)).astype(np.uint8)
    good[:, :, 20] += 5
    contents = {"good": good, "negative counts": good.astype(np.int16) - 3,
                "fractional counts": good + 0.5, "NaN counts": np.where(good > 3, np.nan, good),
                "infinite counts": np.where(good > 3, np.inf, good),
                "huge counts": good.astype(np.int64) * 2**60, "float 1e308": np.where(good > 0, 1e308, 0.0),
                "a 2-D array": good[:, :, 0], "a 4-D array": good[None, None],
                "no time bins": good[:, :, :0], "one pixel": good[:1, :1],
                "bool counts": good > 0, "complex counts": good + 1j, "text": np.array(["a", "b"])}
    for name, a in contents.items():
        for ext in ("npy", "npz", "mat"):
            p = tmp / f"cube{rng.integers(1 << 30)}.{ext}"
            if ext == "npy":
                np.save(p, a)
            elif ext == "npz":
                np.savez(p, counts=a)
            else:
                try:
                    scipy.io.savemat(p, {"hst": a})
                except Exception:   # noqa: BLE001 - scipy cannot write that kind: nothing to read
                    continue
            yield f"{name} ({ext})", p
            if name == "good":
                for mname, data in _mutations(p.read_bytes(), rng, 8, 12):
                    q = tmp / f"cut{rng.integers(1 << 30)}.{ext}"
                    q.write_bytes(data)
                    yield f"good {ext} {mname}", q


@pytest.mark.slow
def test_fuzz_histogram_cubes(tmp_path, rng, capsys, caplog):
    tally = Tally("histogram cubes")
    for name, path in _cube_files(tmp_path, rng):
        tally.check(name, ["recon", str(path), "--time-unit-ps", "80", "--pulse-rms-ps", "170",
                           "--periods", "1000"], capsys, caplog)
    tally.done()
