"""Before/after in one run against another revision of this checkout, not a copy kept in the tree:
``spdepth bench recon --before REV``, ``bench surfaces --before REV`` and ``bench startup --before``.

:func:`package_dir` exports a git revision (``git archive``) into a folder under the temp
directory named by its commit (kept, so its numba cache stays warm for the next run) and returns a
directory that holds it as ``spdepth``: put first on PYTHONPATH, a new interpreter imports that
revision. :func:`side_by_side` runs a benchmark module of both revisions in turn, each in a new
process (a burst of other work on the machine lands on both), and prints their outputs and the
ratios of the figures they share.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

#: The checkout this module belongs to (acq/commands/bench/before.py -> the repository's root).
CHECKOUT = Path(__file__).resolve().parents[3]


def package_dir(before: str) -> str:
    """A directory holding ``before`` as ``spdepth``: ``before`` itself when it is such a directory
    (another checkout linked there), else the git revision of this checkout it names, exported."""
    if (Path(before) / "spdepth").is_dir():
        return str(before)
    try:
        sha = subprocess.run(["git", "-C", str(CHECKOUT), "rev-parse", "--verify", f"{before}^{{commit}}"],
                             capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError) as exc:
        raise SystemExit(f"--before {before}: neither a folder holding spdepth nor a revision of "
                         f"{CHECKOUT} ({getattr(exc, 'stderr', '') or exc})".strip()) from None
    root = Path(tempfile.gettempdir()) / f"spdepth-before-{sha[:12]}"
    tree, pkg = root / "tree", root / "pkg"
    if not (pkg / "spdepth").exists():
        tree.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "-C", str(CHECKOUT), "archive", sha], capture_output=True, check=True)
        subprocess.run(["tar", "-x", "-C", str(tree)], input=archive.stdout, check=True)
        pkg.mkdir(exist_ok=True)
        (pkg / "spdepth").symlink_to(tree, target_is_directory=True)
    return str(pkg)


def run_module(pkgdir: str | None, module: str, argv: list[str]) -> str:
    """stdout of ``python -m module argv`` in a new process, importing spdepth from ``pkgdir``
    (None: this checkout, as installed)."""
    env = dict(os.environ)
    if pkgdir:
        env["PYTHONPATH"] = os.pathsep.join([pkgdir] + [p for p in [env.get("PYTHONPATH")] if p])
    out = subprocess.run([sys.executable, "-m", module, *argv], env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{module} {' '.join(argv)} ({pkgdir or 'this checkout'}) exited {out.returncode}: "
                         f"{out.stderr.strip()[-800:]}")
    return out.stdout


def numbers(line: str) -> list[float]:
    """The numbers of a line of a benchmark's table ("1,234,567", "1.97x", "nan")."""
    out = []
    for tok in line.split():
        tok = tok.rstrip("x%:").replace(",", "")
        try:
            out.append(float(tok))
        except ValueError:
            continue                        # a word of the line, not a number
    return out


def side_by_side(module: str, argv: list[str], before: str, rounds: int,
                 rows: Callable[[str], dict[str, list[float]]], columns: list[str]) -> None:
    """Run ``module`` of the revision ``before`` and of this checkout in turn, ``rounds`` times each,
    print the last output of each, then per row and column the best of each side (larger is
    better) and after / before. ``rows(stdout)``: {row name: the figures in ``columns``' order}."""
    pkg = package_dir(before)
    label = before if os.path.isdir(before) else f"{before} ({Path(pkg).parent.name.split('-')[-1]})"
    sides = {f"before: {label}": pkg, "after: this checkout": None}
    best: dict[str, dict[str, list[float]]] = {s: {} for s in sides}
    last: dict[str, str] = {}
    for _ in range(rounds):
        for side, pkgdir in sides.items():
            last[side] = run_module(pkgdir, module, argv)
            for name, vals in rows(last[side]).items():
                old = best[side].setdefault(name, vals)
                best[side][name] = [max(a, b) for a, b in zip(old, vals)]
    for side in sides:
        print(f"--- {side} (the last of {rounds} runs, taken in turn with the other side's)")
        print(last[side].rstrip())
    b_side, a_side = list(sides)
    print(f"--- best of {rounds} runs each, after / before")
    print(f"{'':<12}" + "".join(f"{c + ', before':>28}{'after':>12}{'ratio':>8}" for c in columns))
    for name, after in best[a_side].items():
        before_vals = best[b_side].get(name)
        if before_vals is None:
            continue
        cells = ""
        for b, a in zip(before_vals, after):
            ratio = a / b if b else float("nan")
            cells += f"{b:>28,.0f}{a:>12,.0f}{ratio:>7.2f}x"
        print(f"{name:<12}{cells}")


def table_rows(names: list[str], pick: list[int], pattern: str = r"^(\S+)\s"
               ) -> Callable[[str], dict[str, list[float]]]:
    """A ``rows`` for :func:`side_by_side`: the lines whose first word (``pattern``'s group) is one
    of ``names``, with the figures after it at the indices ``pick``."""
    rx = re.compile(pattern)

    def rows(text: str) -> dict[str, list[float]]:
        out = {}
        for line in text.splitlines():
            m = rx.match(line)
            if m and m.group(1) in names:
                vals = numbers(line[m.end():])
                out[m.group(1)] = [vals[i] for i in pick]
        return out

    return rows
