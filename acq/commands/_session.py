"""What ``spdepth scan``, ``replay`` and ``demo`` share: a progress bar fed by the session's
snapshots, and running a session to its summary and exit status (their options are declared in
``acq.params``)."""

from __future__ import annotations

import json
import sys
import threading

from spdepth.acq.commands import (EXIT_DEVICE, EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK,
                                  Terminated)


class PreparingNotice:
    """One line on stderr when a command has not started scanning (or replaying) ``after_s``
    after it began: on a fresh install numba compiles every kernel on its first use, a minute or
    more in which nothing else is printed. Use as a context manager around opening the
    instruments and running the session; set ``session`` once it exists."""

    def __init__(self, label: str, after_s: float = 10.0):
        self.label = label
        self.session = None
        self._timer = threading.Timer(after_s, self._say)
        self._timer.daemon = True

    def __enter__(self) -> "PreparingNotice":
        self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self._timer.cancel()

    def _say(self) -> None:
        if self.session is not None and self.session.state.value not in ("idle", "armed"):
            return
        print(f"spdepth {self.label}: preparing; the first run after an install compiles the "
              f"numerical kernels (a minute or two), later runs load them from numba's cache",
              file=sys.stderr, flush=True)


class SessionProgress:
    """The one progress bar (``acq.report.ProgressBar``: pixels complete of all, detections/s,
    state) fed by snapshots at 10 Hz; no subscriber at all when it draws nothing (not a terminal),
    since each snapshot takes the GIL from the scan. It counts pixels that reached the target: a
    time limit flags the rest final, and a bar of final pixels would jump to full at it."""

    def __init__(self, session, label: str):
        from spdepth.acq.report import ProgressBar

        self._bar = ProgressBar(label, session.plan.nx * session.plan.ny)
        self._sub = session.subscribe(self._update, max_hz=10) if self._bar.enabled else None

    def _update(self, snap) -> None:
        self._bar(snap.pixels_complete, snap.pixels_total)
        self._bar.update(0, f"{snap.detections_per_s / 1e6:.2f} Mdet/s, {snap.state}, "
                            f"lost {snap.lost_spans}")

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
        self._bar.close()


def run_session(session, label: str) -> bool:
    """Run with a progress bar. Ctrl-C or SIGTERM aborts cleanly (the session writes its files);
    returns whether it was interrupted, so the caller still reports the summary."""
    bar = SessionProgress(session, label)
    try:
        session.run()
        return False
    except KeyboardInterrupt as exc:
        what = "terminated" if isinstance(exc, Terminated) else "interrupted"
        print(f"spdepth {label}: {what}; the recording and maps so far are kept", file=sys.stderr)
        return True
    finally:
        bar.close()


def exit_status(session, interrupted: bool) -> int:
    """The documented exit status of a session's command (``acq.cli``)."""
    from spdepth.drivers.errors import DeviceError

    if interrupted:
        return EXIT_INTERRUPTED
    if session.state.value == "done":
        return EXIT_OK
    return EXIT_DEVICE if isinstance(session.error, DeviceError) else EXIT_FAILED


def report(summary: dict, as_json: bool, label: str) -> None:
    """Print the summary: one JSON object as the last stdout line, or a few lines for people."""
    if as_json:
        print(json.dumps(summary))
        return
    from spdepth.acq.report import plural

    print(f"{label}: {summary['state']}, {summary['pixels'] - summary['flagged']}/"
          f"{summary['pixels']} pixels complete, {summary['detections']} detections "
          f"({summary['detections_per_s'] / 1e6:.2f} M/s), {plural(summary['passes'], 'pass')}, "
          f"{plural(summary['lost_spans'], 'lost span')}; files in {summary['out']}")
    if summary["flagged"]:
        print(f"  flagged pixels: {summary['flag_reasons']} (maps.npz acq_flags shows which)")
    for w in summary.get("warnings", ()):
        print(f"  warning: {w}")
    if summary["error"]:
        print(f"  error: {summary['error']}")
