"""What ``spdepth scan``, ``replay`` and ``demo`` share: output directory rules, estimator options,
a progress bar fed by the session's snapshots, the files and the one-line JSON summary."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from spdepth.acq.commands._args import positive_float, positive_int
from spdepth.recon.errors import InputError

METHODS = ("uos", "ml", "lmf", "spatial")


def add_output_arguments(parser: argparse.ArgumentParser, *, out_required: bool = True) -> None:
    parser.add_argument("--out", required=out_required, metavar="DIR",
                        help="directory for recording.ptu, events.jsonl, maps.npz, maps.png, run.json")
    parser.add_argument("--overwrite", action="store_true",
                        help="write into DIR even if it is not empty")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON summary object as the last stdout line")


def add_recon_arguments(parser: argparse.ArgumentParser, default_method: str | None = "uos") -> None:
    parser.add_argument("--method", choices=METHODS, default=default_method,
                        help=f"estimator for the maps (default {default_method or 'as recorded'}); "
                             "spatial shows ml while the scan runs and replaces it at the end")
    parser.add_argument("--pulse-rms-ps", type=positive_float, metavar="PS",
                        help="pulse RMS width (default: the simulated scene's, or estimated from "
                             "the first pixels to complete)")


def prepare_out_dir(path: str, overwrite: bool) -> Path:
    """The output directory, created; an existing non-empty one only with ``--overwrite``."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise InputError(f"--out {out} is not empty (pass --overwrite to write into it)")
        for name in ("recording.ptu", "events.jsonl", "maps.npz", "maps.png", "run.json"):
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    return out


class SessionProgress:
    """A tqdm bar (pixels, detections/s, ETA) on a terminal, fed by snapshots at 10 Hz; silent
    when stderr is not a terminal (tqdm's ``disable=None``)."""

    def __init__(self, session, label: str):
        from tqdm import tqdm

        self._bar = tqdm(total=session.plan.nx * session.plan.ny, desc=label, unit="px",
                         disable=None, file=sys.stderr, dynamic_ncols=True)
        # no terminal, no bar: no subscriber either (each snapshot takes the GIL from the scan)
        self._sub = None if self._bar.disable else session.subscribe(self._update, max_hz=10)

    def _update(self, snap) -> None:
        self._bar.n = snap.pixels_final
        self._bar.set_postfix_str(f"{snap.detections_per_s / 1e6:.2f} Mdet/s, "
                                  f"{snap.state}, lost {snap.lost_spans}", refresh=False)
        self._bar.refresh()

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
        self._bar.close()


def run_session(session, label: str):
    """Run with a progress bar; Ctrl-C aborts cleanly (files kept) and exits 130 afterwards."""
    bar = SessionProgress(session, label)
    try:
        state = session.run()
    except KeyboardInterrupt:
        bar.close()
        print(f"spdepth {label}: interrupted; the recording and maps so far are kept",
              file=sys.stderr)
        raise
    bar.close()
    return state


def finish_outputs(session, out: Path, title: str) -> dict:
    """Write maps.png next to the session's files; return the JSON summary."""
    from spdepth.acq.report import render_maps_png

    maps = session.maps()
    render_maps_png(out / "maps.png", maps, title=title)
    snap = session.snapshot()
    run = session.run_record()
    return {
        "state": session.state.value, "out": str(out),
        "error": run["error"],
        "pixels": snap.pixels_total, "flagged": len(run["flagged_pixels"]),
        "flag_reasons": run["flag_reasons"],
        "detections": snap.detections, "detections_per_s": round(snap.detections_per_s, 1),
        "stream_s": session.stream_s, "passes": snap.passes,
        "lost_spans": snap.lost_spans, "lost_records": snap.lost_records,
        "faults_seen": len(run["faults_seen"]), "recon_max_lag_pixels": session.recon.max_lag,
        "elapsed_s": round(snap.elapsed_s, 3),
    }


def report(summary: dict, as_json: bool, label: str) -> int:
    """Print the summary; exit status 0 when the session is done, 1 when it failed or aborted."""
    if as_json:
        print(json.dumps(summary))
    else:
        print(f"{label}: {summary['state']}, {summary['pixels'] - summary['flagged']}/"
              f"{summary['pixels']} pixels complete, {summary['detections']} detections "
              f"({summary['detections_per_s'] / 1e6:.2f} M/s), {summary['passes']} passes, "
              f"{summary['lost_spans']} lost spans; files in {summary['out']}")
        if summary["flagged"]:
            print(f"  flagged pixels: {summary['flag_reasons']} (run.json lists them)")
        if summary["error"]:
            print(f"  error: {summary['error']}")
    return 0 if summary["state"] == "done" else 1


__all__ = ["add_output_arguments", "add_recon_arguments", "prepare_out_dir", "run_session",
           "finish_outputs", "report", "positive_int"]
