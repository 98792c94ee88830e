"""Frames as the API and the UI carry them: one JSON object per complete frame.

``{"n": cursor, "source", "frame", "origin": ns, "enter": [ns|null per stage],
"exit": [ns|null per stage], "delay_ms": end - origin}``, timestamps moved to the relay's
clock by the run's correction; a block adds the run, its stages and the paging cursor.
"""

from __future__ import annotations

import numpy as np

from probes.stats import MISSING


def frame_dicts(n: np.ndarray, source: np.ndarray, frame: np.ndarray, origin: np.ndarray, end: np.ndarray,
                enter: np.ndarray, exit_: np.ndarray, correction_ns: int) -> list[dict]:
    """One dict per row; ``enter``/``exit_`` are (rows, stages) with MISSING where absent."""
    return [
        {"n": k, "source": s, "frame": f, "origin": o - correction_ns,
         "enter": _corrected(en, correction_ns), "exit": _corrected(ex, correction_ns), "delay_ms": (e - o) / 1e6}
        for k, s, f, o, e, en, ex in zip(n.tolist(), source.tolist(), frame.tolist(), origin.tolist(),
                                         end.tolist(), enter.tolist(), exit_.tolist())
    ]


def block(node: str, run: str, stages: list[str], frames: list[dict], since: int, newest: int,
          correction_ns: int, clock: str, kinds: dict[str, str] | None = None) -> dict:
    """A page of frames: ``cursor`` is the n of its last frame (``since`` when empty), ``newest``
    the n of the newest frame there is; ``kinds``: stage name -> element factory."""
    return {"node": node, "run": run, "stages": stages, "kinds": kinds or {}, "correction_ns": correction_ns,
            "clock": clock, "cursor": frames[-1]["n"] if frames else since, "newest": newest, "frames": frames}


def _corrected(values: list[int], corr: int) -> list[int | None]:
    return [None if v == MISSING else v - corr for v in values]
