"""Honesty of depths and their uncertainties without truth: the split-half check.

Every pixel's detections are split into two halves (alternate detections, in detection order), each
half is reconstructed alone with the model (binning and pulse) resolved on the whole file, and
where both halves report a depth, the share that agree within 3 and within 1 combined sigma
(``|d_a - d_b| <= k sqrt(s_a^2 + s_b^2)``) is counted. For honest depths and uncertainties the two
halves are independent draws: about 99.7% agree within 3 sigma and 68% within 1 (a heavy tail of
failures, e.g. a background cluster taken for a return, shows in the 3-sigma share; uncertainties
too large or too small move the 1-sigma share). Also printed: the share of pixels with a depth in
the whole file and in each half, and for ml with a Gaussian pulse the pulse model's dispersion on
the whole file (``recon.detect.dispersion_of``: below 1, the detections lie closer to their depths
than the model says, and the model's uncertainties were too wide), by which each half's
uncertainties are scaled too (its own, measured on it).

Run as ``spdepth bench honesty FILE [--methods ml,spatial] [--time-unit-ps PS] ...``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

# numpy and the estimators are imported where used: ``spdepth bench honesty --help`` loads neither


def split_halves(store: PhotonStore) -> tuple[PhotonStore, PhotonStore]:
    """The two halves of every pixel's detections: the 1st, 3rd, ... and the 2nd, 4th, ..."""
    import numpy as np

    from spdepth.recon.photons import PhotonStore

    counts = np.diff(store.offsets)
    rank = np.arange(store.n_photons) - np.repeat(store.offsets[:-1], counts)
    pix = np.repeat(np.arange(store.n_pixels), counts)
    out = []
    for parity in (0, 1):
        keep = (rank % 2) == parity
        out.append(PhotonStore.from_pixel_indices(pix[keep], store.times[keep], store.shape, store.time_unit_s))
    return out[0], out[1]


def resolved_settings(settings: ReconSettings, used: dict) -> ReconSettings:
    """``settings`` with the binning and the pulse a reconstruction resolved (``used``: its
    ``settings`` record), so the halves are fitted with the same model."""
    from spdepth.recon.model import Binning, Irf

    b = Binning.from_dict(used["binning"])
    if used.get("irf"):
        return dataclasses.replace(settings, binning=b, irf=Irf.from_dict(used["irf"]), pulse_rms_s=None)
    return dataclasses.replace(settings, binning=b, pulse_rms_s=float(used["pulse_rms_s"]), irf=None)


def agreement(a, b) -> dict:
    """Split-half figures of two maps of the same scene. With several surfaces, those of surface 0,
    and under "surfaces" each surface's where both halves find as many surfaces and that one not weak
    (the weak are marked as what background alone could have made)."""
    import numpy as np

    da, db = np.asarray(a.depth_m, float), np.asarray(b.depth_m, float)
    sa = np.asarray(a.uncertainty_s, float)
    sb = np.asarray(b.uncertainty_s, float)
    if da.ndim == 3:
        same = np.asarray(a.surfaces) == np.asarray(b.surfaces)
        per = [_agree(da[k], db[k], sa[k], sb[k], same & ~np.asarray(a.weak[k]) & ~np.asarray(b.weak[k]))
               for k in range(da.shape[0])]
        out = _agree(da[0], db[0], sa[0], sb[0], None)
        out["surfaces"] = per
        return out
    return _agree(da, db, sa, sb, None)


def _agree(da, db, sa, sb, where) -> dict:
    import numpy as np

    c2 = 299_792_458.0 / 2.0
    both = np.isfinite(da) & np.isfinite(db)
    if where is not None:
        both &= where
    z = np.abs(da - db)[both] / (c2 * np.hypot(sa[both], sb[both]))
    n = int(both.sum())
    return {"pixels": int(da.size), "depth_a": float(np.isfinite(da).mean()), "depth_b": float(np.isfinite(db).mean()),
            "both": n, "within_3_sigma": float(np.mean(z <= 3.0)) if n else None,
            "within_1_sigma": float(np.mean(z <= 1.0)) if n else None,
            "median_sigma_m": float(np.median(c2 * np.hypot(sa[both], sb[both]) / np.sqrt(2))) if n else None}


def split_half(store: PhotonStore, settings: ReconSettings) -> dict:
    """Reconstruct ``store`` whole and its two halves alone; the figures of :func:`agreement` plus
    the share of pixels with a depth in the whole and the decision's settings."""
    import numpy as np

    from spdepth.recon.estimate import reconstruct

    full = reconstruct(store, settings)
    fixed = resolved_settings(settings, full.settings)
    half_a, half_b = split_halves(store)
    a, b = reconstruct(half_a, fixed), reconstruct(half_b, fixed)
    depth = np.asarray(full.depth_m, float)
    has = np.isfinite(depth) if depth.ndim == 2 else np.isfinite(depth).any(axis=0)
    out = {"method": settings.method, "depth_full": float(has.mean()),
           "pulse_dispersion": full.settings.get("pulse_dispersion")}
    out.update(agreement(a, b))
    if "detection" in full.settings:
        out["detection"] = full.settings["detection"].get("rule")
    return out


def bench(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="spdepth bench honesty", description=__doc__.split("\n\n")[0])
    parser.add_argument("file", help=".mat or PicoQuant file (a real scan, or one from spdepth simulate)")
    parser.add_argument("--methods", default="ml,spatial", help="estimators, comma-separated (default ml,spatial)")
    parser.add_argument("--time-unit-ps", type=float, default=None, help="raw time unit (.mat files)")
    parser.add_argument("--window-ps", default=None, help="START:STOP (ps); default from the data")
    parser.add_argument("--bin-ps", type=float, default=None)
    parser.add_argument("--pulse-rms-ps", type=float, default=None, help="default: measured from the data")
    parser.add_argument("--max-photons", type=int, default=None)
    parser.add_argument("--reflectors", default=1, type=_surfaces, metavar="K|auto",
                        help="surfaces per pixel (default 1); with several, each surface's figures too")
    parser.add_argument("--json", action="store_true", help="one JSON object per estimator")
    args = parser.parse_args(argv)
    from spdepth.acq.readers import read_photons
    from spdepth.recon.model import METHODS, Binning, ReconSettings

    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        parser.error(f"--methods: unknown {', '.join(bad)} (choose from {', '.join(METHODS)})")
    unit_s = None if args.time_unit_ps is None else args.time_unit_ps * 1e-12
    store = read_photons(args.file, time_unit_s=unit_s).store
    if store is None:
        # a histogram cube keeps no detection order to alternate over
        parser.error(f"{args.file} is a count cube: its halves are drawn at random by "
                     f"spdepth bench halves {args.file} (each count to one half)")
    binning = None
    if args.window_ps or args.bin_ps:
        window_s = None
        if args.window_ps:
            lo, hi = (float(v) * 1e-12 for v in args.window_ps.split(":"))
            window_s = (lo, hi)
        bin_s = None if args.bin_ps is None else args.bin_ps * 1e-12
        if window_s is not None and bin_s is not None:
            binning = Binning.from_window(store.time_unit_s, window_s, bin_s)
        else:
            binning = Binning.from_data(store.times, store.time_unit_s, window_s=window_s, bin_s=bin_s,
                                        pulse_rms_s=None if args.pulse_rms_ps is None else args.pulse_rms_ps * 1e-12)
    per_pixel = store.n_photons / store.n_pixels
    print(f"{args.file}: {store.shape[0]}x{store.shape[1]} pixels, {per_pixel:.2f} detections per pixel; "
          f"halves: alternate detections of each pixel, model resolved on the whole file")
    reflectors = args.reflectors
    for method in methods:
        settings = ReconSettings(method=method, binning=binning, max_photons=args.max_photons, reflectors=reflectors,
                                 pulse_rms_s=None if args.pulse_rms_ps is None else args.pulse_rms_ps * 1e-12)
        r = split_half(store, settings)
        if args.json:
            print(json.dumps(r))
            continue
        first = "surface 1, weak included, " if "surfaces" in r else ""
        print(f"{method:>8}: depth on {100 * r['depth_full']:5.1f}% (halves {100 * r['depth_a']:5.1f}% / "
              f"{100 * r['depth_b']:5.1f}%); {first}both halves {_shares(r)}"
              + (f"; pulse model's dispersion {r['pulse_dispersion']['dispersion']:.2f}" if r["pulse_dispersion"] else ""))
        for k, rk in enumerate(r.get("surfaces", [])):
            print(f"          surface {k + 1}, not weak, as many surfaces in both halves: {_shares(rk)}")
    return 0


def _surfaces(text: str):
    """--reflectors: "auto" or a whole number (ReconSettings says which are allowed)."""
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"K (a whole number) or auto, got {text!r}") from None


def _shares(r: dict) -> str:
    w3 = "-" if r["within_3_sigma"] is None else f"{100 * r['within_3_sigma']:.1f}%"
    w1 = "-" if r["within_1_sigma"] is None else f"{100 * r['within_1_sigma']:.1f}%"
    return f"{r['both']:6d} px: within 3 sigma {w3:>6}, within 1 sigma {w1:>6}"


if __name__ == "__main__":
    raise SystemExit(bench(__import__("sys").argv[1:]))
