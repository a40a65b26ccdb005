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
    """What a command says before it starts scanning (or replaying): one line on stderr for each
    kernel numba compiles (a fresh install compiles each on its first use, a minute or more in all
    in which nothing else would be printed), with how many so far and the seconds since the
    command began preparing (:class:`CompileNotice`); else, when it still has not started after
    ``after_s``, one line saying it is preparing. Use as a context manager around opening the
    instruments and running the session; set ``session`` once it exists."""

    def __init__(self, label: str, after_s: float = 10.0):
        self.label = label
        self.session = None
        self._timer = threading.Timer(after_s, self._say)
        self._timer.daemon = True
        self._compiles = CompileNotice(f"spdepth {label}")

    def __enter__(self) -> "PreparingNotice":
        self._compiles.__enter__()
        self._timer.start()
        return self

    def __exit__(self, *exc) -> None:
        self._timer.cancel()
        self._compiles.__exit__(*exc)

    def _say(self) -> None:
        if self._compiles.count or (self.session is not None
                                    and self.session.state.value not in ("idle", "armed")):
            return
        print(f"spdepth {self.label}: preparing; the first run after an install compiles the "
              f"numerical kernels (a minute or two), later runs load them from numba's cache",
              file=sys.stderr, flush=True)


class CompileNotice:
    """While active, one line on stderr as numba starts compiling each of our kernels (a cache
    miss: the first run after an install or an upgrade), e.g. ``spdepth demo: compiling kernel 3,
    recon.kernels.ml_kernel (first run; later runs load it from numba's cache), 12 s in``.
    Kernels a kernel calls compile inside it and are not listed; loads from the cache say
    nothing. Any thread's compiles count (numba compiles one at a time)."""

    def __init__(self, prefix: str, stream=None):
        self.prefix = prefix
        self.count = 0
        self._stream = stream
        self._depth = threading.local()
        self._t0 = 0.0
        self._listener = None

    def __enter__(self) -> "CompileNotice":
        import time

        from numba.core import event

        notice = self

        class _Listener(event.Listener):
            def on_start(self, ev):
                notice._started(ev.data["dispatcher"])

            def on_end(self, ev):
                notice._depth.n = getattr(notice._depth, "n", 1) - 1

        self._t0 = time.monotonic()
        self._listener = _Listener()
        event.register("numba:compile", self._listener)
        return self

    def __exit__(self, *exc) -> None:
        from numba.core import event

        if self._listener is not None:
            event.unregister("numba:compile", self._listener)
            self._listener = None

    def _started(self, dispatcher) -> None:
        import time

        depth = getattr(self._depth, "n", 0)
        self._depth.n = depth + 1
        func = getattr(dispatcher, "py_func", None)
        module = getattr(func, "__module__", "") or ""
        if depth or not module.startswith("spdepth."):
            return
        self.count += 1
        name = f"{module.removeprefix('spdepth.')}.{func.__name__}"
        print(f"{self.prefix}: compiling kernel {self.count}, {name} (first run; later runs load "
              f"it from numba's cache), {time.monotonic() - self._t0:.0f} s in",
              file=self._stream or sys.stderr, flush=True)


class SessionProgress:
    """The one progress bar (``acq.report.ProgressBar``: pixels complete of all, detections/s,
    state) fed at 10 Hz by ``Session.progress`` (figures only: a snapshot's map copies cost a
    large frame's scan most of its speed), on a thread of its own; none at all when it draws
    nothing (not a terminal). It counts pixels that reached the target: a time limit flags the
    rest final, and a bar of final pixels would jump to full at it."""

    PERIOD_S = 0.1

    def __init__(self, session, label: str):
        from spdepth.acq.report import ProgressBar

        self._session = session
        self._bar = ProgressBar(label, session.plan.nx * session.plan.ny)
        self._closed = threading.Event()
        self._thread = None
        if self._bar.enabled:
            self._thread = threading.Thread(target=self._run, name="session-progress", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        while True:
            ended = self._session.ended.wait(self.PERIOD_S) or self._closed.is_set()
            self._update(self._session.progress())
            if ended:
                return

    def _update(self, p: dict) -> None:
        self._bar(p["pixels_complete"], p["pixels_total"])
        self._bar.update(0, f"{p['detections_per_s'] / 1e6:.2f} Mdet/s, {p['state']}, "
                            f"lost {p['lost_spans']}")

    def close(self) -> None:
        self._closed.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self._bar.close()


class OutputsProgress:
    """The bar of the files a command writes after its session (``acq.api.finish_session``'s
    ``progress``: maps.png, points.ply; seconds on a large frame), on a terminal only: files
    written of all, and the one being written."""

    def __init__(self, label: str):
        self.label = label
        self._bar = None

    def __call__(self, name: str, done: int, total: int) -> None:
        from spdepth.acq.report import ProgressBar

        if self._bar is None:
            self._bar = ProgressBar(f"{self.label} files", total, unit="file")
        self._bar(done, total)
        self._bar.update(0, f"writing {name}" if name else "written")
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None


WRITER_MODULES = ("matplotlib.figure", "matplotlib.backends.backend_agg", "spdepth.acq.report",
                  "spdepth.acq.mapdefs", "spdepth.acq.points", "plyfile")
"""What ``acq.api.finish_session`` imports to write maps.png and points.ply: imported on a thread
while the session runs (half a second here that a time-limited scan waited for after its end)."""


def _import_writers(session) -> None:
    import importlib
    import logging

    from spdepth.acq.session import SessionState

    # once scanning: while armed the session loads its kernels, and imports compete with them for
    # the interpreter; a time limit counts from RUNNING (a session that ends first: at once)
    session.wait_for_state(SessionState.RUNNING, timeout_s=None)

    for name in WRITER_MODULES:
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - finish_session imports it again and says why
            logging.getLogger(__name__).debug("importing %s ahead failed: %s", name, exc)



def compile_live_apart(request, label: str):
    """On a cold numba cache (a first run), the live estimator's kernels and the return test's in a
    second process (``recon.estimate.compile_apart``), started now, with a line saying so; the
    session's warm-up waits for it and then loads them. On the warm-up's own thread their compile
    held the interpreter the scan's threads run in (numba compiles holding it). None when they are
    cached, or a process started earlier compiles them (the demo's)."""
    from spdepth.recon.estimate import compile_apart
    from spdepth.recon.model import ReconSettings

    settings = ReconSettings(method=request.method, max_photons=request.target, reflectors=request.reflectors)
    child = compile_apart([settings], decide=True)
    if child is not None:
        print(f"spdepth {label}: compiling {request.method}'s and the return test's kernels in a second process "
              f"while the scan runs (first run; later runs load them from numba's cache)", file=sys.stderr)
    return child

def run_session(session, label: str) -> bool:
    """Run with a progress bar. Ctrl-C or SIGTERM aborts cleanly (the session writes its files);
    returns whether it was interrupted, so the caller still reports the summary. A session with
    an output folder imports the writers of its PNG and points meanwhile (``WRITER_MODULES``)."""
    if session.out_dir is not None:
        threading.Thread(target=_import_writers, args=(session,), name="import-writers",
                         daemon=True).start()
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
        from spdepth.acq.api import no_pixel_cause

        # a run that completed no pixel is not done: exit 1 (report() names the likely cause)
        return EXIT_FAILED if no_pixel_cause(session) else EXIT_OK
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
    pileup = summary.get("pileup")
    if pileup and pileup.get("applied"):
        print(f"  pile-up: {pileup['reason']}")
    if summary["flagged"]:
        print(f"  flagged pixels: {summary['flag_reasons']} (maps.npz acq_flags shows which)")
    for w in summary.get("warnings", ()):
        print(f"  warning: {w}")
    if summary["error"]:
        print(f"  error: {summary['error']}")
    if summary.get("no_pixel_complete"):
        print(f"  error: no pixel completed: {summary['no_pixel_complete']}")
