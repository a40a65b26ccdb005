"""One JSON encoding (``acq.jsonable``) for run.json and the front ends' summaries."""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from spdepth.acq.flags import AcqFlag
from spdepth.acq.jsonable import jsonable, write_json_atomic


@dataclass(frozen=True)
class _Identity:
    model: str
    serial: np.int64


def test_what_json_cannot_write_is_made_plain(tmp_path):
    value = {1: (np.float32(0.5), np.bool_(True)), "flag": AcqFlag.COMPLETE, "nan": float("nan"),
             "inf": np.float64("inf"), "map": np.arange(3, dtype=np.uint8),
             "device": _Identity("sim", np.int64(7))}
    out = jsonable(value)
    assert out == {"1": [0.5, True], "flag": "COMPLETE", "nan": None, "inf": None,
                   "map": [0, 1, 2], "device": {"model": "sim", "serial": 7}}
    assert json.loads(json.dumps(out, allow_nan=False)) == out        # strict JSON
    write_json_atomic(tmp_path / "run.json", value)
    assert json.loads((tmp_path / "run.json").read_text()) == out
    assert [p.name for p in tmp_path.iterdir()] == ["run.json"]       # no temporary left
