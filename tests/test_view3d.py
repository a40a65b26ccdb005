"""The window's 3-D view: a point cloud that fills in with the scan where OpenGL exists (CI: under
xvfb-run with Mesa, see .ci/run), and a note instead of it where it does not (offscreen)."""

from __future__ import annotations

import numpy as np
import pytest

from spdepth.gui.sources import SourceSpec
from spdepth.gui.view3d import opengl_unavailable


def _run(qtbot, win, tmp_path):
    spec = SourceSpec(kind="sim", scene="bust", size=(16, 20), target=5, out_root=str(tmp_path))
    win.show_view("3d")
    assert win.start_run(spec, out_dir=None)
    qtbot.waitUntil(lambda: win.snap is not None and win.snap.state == "done", timeout=120_000)
    win.refresh()
    # the view is set from the last snapshot: one point per estimated pixel
    qtbot.waitUntil(lambda: win.view3d.n_points == int(np.isfinite(win.snap.depth_m).sum()),
                    timeout=30_000)


def test_3d_view_draws_the_points(qtbot, win, tmp_path):
    reason = opengl_unavailable()
    if reason is not None:
        pytest.skip(f"no OpenGL here ({reason}); .ci/run runs this under xvfb-run")
    _run(qtbot, win, tmp_path)
    v = win.view3d
    assert v.available
    assert v.n_points == int(np.isfinite(win.snap.depth_m).sum()) > 0.9 * 16 * 20
    img = v.grab_view()
    a = np.frombuffer(img.constBits(), np.uint8).reshape(img.height(), img.bytesPerLine())
    # white background with coloured points: not a blank (all one colour) picture
    assert img.width() > 100 and len(np.unique(a)) > 20
    assert (a < 200).mean() > 0.002
    # a K=2 map gets one colour per surface
    two = np.stack([win.snap.depth_m, win.snap.depth_m + 0.5])
    v.set_maps(two, np.stack([win.snap.signal] * 2))
    assert v.n_points == 2 * int(np.isfinite(win.snap.depth_m).sum())
    # weak surfaces far behind the scene: grey, and the framing stays on the confident points
    far = np.stack([win.snap.depth_m, win.snap.depth_m + 50.0])
    weak = np.zeros(far.shape, bool)
    weak[1] = True
    v.reset_camera()
    v.set_maps(far, np.stack([win.snap.signal] * 2), weak)
    centre = v.gl.opts["center"]
    assert abs(centre.y() - float(np.nanmedian(win.snap.depth_m))) < 1.0      # y shows the range
    assert v.gl.opts["distance"] < 2.5 * 5.0


def test_window_opens_without_opengl(qtbot, win, tmp_path):
    if opengl_unavailable() is None:
        pytest.skip("OpenGL is available here: the note is not shown")
    v = win.view3d
    assert not v.available and v.reason
    _run(qtbot, win, tmp_path)
    assert v.n_points == int(np.isfinite(win.snap.depth_m).sum())   # computed, just not drawn


def test_missing_x_libraries_are_named_before_qt_aborts():
    from spdepth.gui.app import missing_libraries, platform_problem

    ldd = ("\tlinux-vdso.so.1 (0x00007ffd)\n\tlibxcb-icccm.so.4 => not found\n"
           "\tlibxcb-keysyms.so.1 => not found\n\tlibxcb.so.1 => /lib/libxcb.so.1 (0x7f)\n"
           "\tlibxcb-icccm.so.4 => not found\n")
    assert missing_libraries(ldd) == ["libxcb-icccm.so.4", "libxcb-keysyms.so.1"]
    env = {"DISPLAY": ":0"}
    line = platform_problem(env, ldd=lambda path: ldd)
    assert "libxcb-icccm.so.4, libxcb-keysyms.so.1" in line
    assert "apt-get install libxcb-icccm4 libxcb-keysyms1" in line
    assert platform_problem(env, ldd=lambda path: "\tlibxcb.so.1 => /lib/libxcb.so.1\n") is None
    assert platform_problem({"QT_QPA_PLATFORM": "offscreen", "DISPLAY": ":0"},
                            ldd=lambda path: ldd) is None
