"""A pty pair in front of a GalvoFirmware, so the real driver opens a real tty path (POSIX).

``PtyLink(fw).start()`` returns a stable path (a symlink in a private temp directory, like the
``/dev/serial/by-id/...`` links udev makes) to the slave side of a pty; a thread on the master side
feeds the firmware. When the emulator is unplugged the link closes the master (the host's reads
and writes then fail with EIO -> SerialException) and removes the symlink; when it is plugged back
in a new pty is made and the symlink points at it again.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import pty
import select
import shutil
import tempfile
import threading
import time
import tty

from spdepth.drivers.sim.galvo_fw import GalvoFirmware, PortUnplugged

log = logging.getLogger("spdepth.sim.pty")


class PtyLink:
    """Serve ``fw`` on a pty. Use as a context manager or call ``start()`` / ``close()``.

    name: file name of the symlink (the path is ``<tempdir>/<name>``)."""

    def __init__(self, fw: GalvoFirmware, name: str = "galvo0"):
        self.fw = fw
        self._dir = tempfile.mkdtemp(prefix="spdepth-pty-")
        self.path = os.path.join(self._dir, name)
        """The tty path the host opens with ``serial.Serial(path)``."""
        self._master = -1
        self._slave = -1
        self._gen = -1
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None
        """An unexpected exception that ended the link thread."""

    def start(self) -> str:
        self.fw.add_listener(self._wake)
        self._plug()
        self._thread = threading.Thread(target=self._run, name=f"pty-link-{self.path}",
                                        daemon=True)
        self._thread.start()
        return self.path

    def __enter__(self) -> "PtyLink":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except BlockingIOError:
            pass   # a wake-up is already pending
        except OSError:
            pass   # closed

    def _plug(self) -> None:
        self._master, self._slave = pty.openpty()
        # Raw slave: no echo, no CR/LF translation, no line buffering; pyserial sets the same
        # when it opens the path, this covers the gap before that.
        tty.setraw(self._slave)
        self._gen = self.fw.generation
        tmp = self.path + ".new"
        os.symlink(os.ttyname(self._slave), tmp)
        os.replace(tmp, self.path)
        log.debug("pty link %s -> %s", self.path, os.ttyname(self._slave))

    def _unplug(self) -> None:
        with contextlib.suppress(FileNotFoundError):   # already gone: unplugged before
            os.unlink(self.path)
        for fd in (self._master, self._slave):
            if fd >= 0:
                os.close(fd)
        self._master = self._slave = -1

    def _run(self) -> None:
        try:
            while not self._closing.is_set():
                if self._master < 0:
                    if self.fw.is_plugged:
                        self._plug()
                    else:
                        self._closing.wait(0.01)
                    continue
                if self.fw.generation != self._gen:
                    self._unplug()
                    continue
                due = self.fw.next_output_due()
                timeout = 0.5 if due is None else max(0.0, due - time.monotonic())
                r, _, _ = select.select([self._master, self._wake_r], [], [], min(timeout, 0.5))
                if self._wake_r in r:
                    os.read(self._wake_r, 4096)
                if self._master in r:
                    try:
                        data = os.read(self._master, 4096)
                    except OSError as e:
                        if e.errno != errno.EIO:
                            raise
                        data = b""   # no host has the slave open; nothing to read
                    if data:
                        try:
                            self.fw.host_write(data, self._gen)
                        except PortUnplugged:
                            continue
                try:
                    out = self.fw.host_read(65536, 0.0, self._gen)
                except PortUnplugged:
                    continue
                if out:
                    os.write(self._master, out)
        except BaseException as e:   # noqa: BLE001 - kept for the owner, see self.error
            log.exception("pty link thread failed")
            self.error = e

    def close(self) -> None:
        self._closing.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(5.0)
        self.fw.remove_listener(self._wake)
        self._unplug()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):             # closed by the other side's unplug
                os.close(fd)
        shutil.rmtree(self._dir, ignore_errors=True)
