"""Issue 32's command-line edges, each one line on stderr and a documented exit status, before any
work: outputs that cannot be written, the one overwrite rule, the benchmarks' usage, a missing
file given to the window."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from spdepth.acq.cli import main

PROC = Path("/proc/self").exists()
needs_proc = pytest.mark.skipif(not PROC, reason="no /proc here (a folder no file can be made in)")


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


@needs_proc
@pytest.mark.parametrize("argv, said", [
    (["recon", "{ptu}", "--png", "/proc/x.png"], "--png /proc/x.png: cannot be written"),
    (["recon", "{ptu}", "--npz", "/proc/x.npz"], "--npz /proc/x.npz: cannot be written"),
    (["recon", "{ptu}", "--save-irf", "/proc/x.csv"], "--save-irf /proc/x.csv: cannot be written"),
    (["recon", "{ptu}", "--ply", "/proc/x.ply", "--fov-deg", "10"], "--ply /proc/x.ply: cannot be written"),
    (["recon", "{ptu}", "other.ptu", "--npz", "/proc/batch"], "--npz /proc/batch: cannot be written"),
    (["simulate", "--scene", "bust", "--size", "8x8", "--ptu", "/proc/x.ptu"],
     "--ptu /proc/x.ptu: cannot be written"),
    (["demo", "--no-window", "--size", "8x8", "--png", "/proc/x.png"], "--png /proc/x.png: cannot be written"),
    (["scan", "--sim", "--size", "4x4", "--out", "/proc/run"], "--out /proc/run: cannot be written"),
    (["bench", "report", "--quick", "--out", "/proc/rep"], "--out /proc/rep: cannot be written"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(argv, said, small_ptu,
                                                                      capsys):
    argv = [a.replace("{ptu}", str(small_ptu)) for a in argv]
    assert main(argv) == 2
    line = _one_line(capsys)
    assert said in line and "(files cannot be created there)" in line


def test_an_existing_output_is_refused_unless_overwrite(small_ptu, tmp_path, capsys):
    session_like = tmp_path / "run"
    session_like.mkdir()
    shutil.copy(small_ptu, session_like / "recording.ptu")
    maps = session_like / "maps.npz"
    maps.write_bytes(b"the session's own maps")
    assert main(["recon", str(session_like / "recording.ptu"), "--npz", str(maps)]) == 2
    assert _one_line(capsys) == (f"spdepth recon: error: --npz {maps} exists (pass --overwrite to "
                                 f"replace it)")
    assert maps.read_bytes() == b"the session's own maps"
    assert main(["recon", str(session_like / "recording.ptu"), "--npz", str(maps),
                 "--overwrite"]) == 0
    assert maps.read_bytes() != b"the session's own maps"
    capsys.readouterr()
    # an input is never an output, --overwrite or not
    assert main(["recon", str(small_ptu), "--npz", str(small_ptu), "--overwrite"]) == 2
    assert "is the input" in _one_line(capsys)
    ptu = tmp_path / "sim.ptu"
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--ptu", str(ptu)]) == 0
    capsys.readouterr()
    before = ptu.read_bytes()
    assert main(["simulate", "--scene", "bust", "--size", "8x8", "--seed", "3", "--ptu", str(ptu)]) == 2
    assert _one_line(capsys) == (f"spdepth simulate: error: --ptu {ptu} exists, and so does "
                                 f"{tmp_path / 'sim.truth.npz'} (pass --overwrite to replace them)")
    assert ptu.read_bytes() == before
    png = tmp_path / "sheet.png"
    png.write_bytes(b"x")
    assert main(["demo", "--no-window", "--size", "8x8", "--png", str(png)]) == 2
    assert "--png" in _one_line(capsys) and png.read_bytes() == b"x"


def test_the_benchmarks_say_what_is_wrong_in_one_line(capsys):
    assert main(["bench"]) == 2
    from spdepth.acq.commands.bench import TARGETS

    assert _one_line(capsys).startswith("spdepth bench: error: give a benchmark: "
                                        + ", ".join(sorted(TARGETS)))
    assert main(["bench", "spatial", "--side", "-3"]) == 2
    assert _one_line(capsys) == ("spdepth bench spatial: error: argument --side: must be a whole "
                                 "number >= 4 and at most 4096, got -3 (see spdepth bench spatial --help)")
    assert main(["bench", "gui", "--target", "0"]) == 2
    assert "--target: must be a whole number >= 1" in _one_line(capsys)
    for target in ("spatial", "gui", "decode"):
        assert main(["bench", target, "--help"]) == 0
        out = capsys.readouterr().out
        options = [ln for ln in out.splitlines() if ln.startswith("  --")]
        # every option has its help on its line or the next: none is a bare name
        lines = out.splitlines()
        for ln in options:
            i = lines.index(ln)
            assert len(ln.split()) > 2 or lines[i + 1].startswith(" " * 10), (target, ln)
    assert "ptufile's compiled decoder" in " ".join(
        (main(["bench", "decode", "--help"]), capsys.readouterr().out)[1].split())


def test_no_benchmark_help_shows_an_unfilled_placeholder(capsys):
    """A benchmark that takes another command's declared options fills their lists ({method_names},
    {scenes}, ...) into its help as the command does (bench halves once showed them raw)."""
    import re

    from spdepth.acq.commands.bench import TARGETS

    for target in sorted(TARGETS):
        assert main(["bench", target, "--help"]) == 0
        out = capsys.readouterr().out
        assert not re.search(r"\{[a-z_]+\}", out), (target, re.findall(r"\{[a-z_]+\}", out))
    assert main(["bench", "halves", "--help"]) == 0
    assert "{lmf,uos,ml,spatial}" in capsys.readouterr().out


def test_the_window_refuses_a_missing_file_in_one_line(capsys, tmp_path):
    assert main(["gui", "--file", str(tmp_path / "nonexistent.mat"), "--exit-after-scan"]) == 2
    assert _one_line(capsys) == f"spdepth gui: error: {tmp_path / 'nonexistent.mat'}: no such file"


def test_bench_honesty_of_a_cube_names_bench_halves(shared_data, capsys):
    # a cube keeps no detection order: the alternate-detection split has nothing to alternate over
    from spdepth.acq.commands.bench.honesty import bench

    with pytest.raises(SystemExit) as exc:
        bench([str(shared_data / "cube" / "art_top.mat"), "--time-unit-ps", "80"])
    assert exc.value.code == 2
    assert "spdepth bench halves" in capsys.readouterr().err


def test_a_benchmark_s_message_exit_is_one_line_not_a_traceback(capsys):
    # bench recon --before with neither a folder nor a revision exits with a message (SystemExit
    # of a string): the bench command said it as a ValueError traceback
    assert main(["bench", "recon", "--before", "/no/such/folder"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("spdepth bench recon: error: --before /no/such/folder") and "Traceback" not in err
    assert err.count("\n") == 1
