"""``spdepth devices``: one line per instrument found (our serial ports and USB tagger, PicoQuant
devices through their libraries, Swabian taggers, NI devices) and one per vendor library that is
not installed. Exit 0 also with nothing attached."""

from __future__ import annotations

import argparse
import json

HELP = "list the instruments this computer reaches and the vendor libraries that are missing"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true",
                        help='print {"instruments": [...], "missing": [...]} as JSON')


def run(args: argparse.Namespace) -> int:
    from spdepth.acq.discovery import find_instruments

    found = find_instruments()
    if args.json:
        print(json.dumps({"instruments": [f.to_dict() for f in found if not f.missing],
                          "missing": [f.to_dict() for f in found if f.missing]}, indent=1))
        return 0
    if not any(not f.missing for f in found):
        print("no instruments found")
    for f in found:
        print(f.line())
    return 0
