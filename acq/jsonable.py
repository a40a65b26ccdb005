"""One JSON encoding for everything we write as JSON: ``run.json`` (``acq.session``) and the
summaries ``spdepth recon --json`` and the other front ends print (``acq.api``)."""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, is_dataclass
from enum import Enum
from pathlib import Path

import numpy as np


def jsonable(value):
    """``value`` with what ``json`` cannot write made plain: a dataclass as its dict, dict keys as
    strings, tuples as lists, an ``Enum`` as its name, NumPy scalars and arrays as Python numbers
    and lists, and a non-finite float as None (strict JSON has no NaN)."""
    if is_dataclass(value) and not isinstance(value, type):
        value = asdict(value)
    if isinstance(value, dict):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, Enum):
        return value.name
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_json_atomic(path: str | Path, data) -> None:
    """``jsonable(data)`` written to a temporary name beside ``path``, synced, then renamed over
    it: a reader never sees half a file."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(jsonable(data), fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


__all__ = ["jsonable", "write_json_atomic"]
