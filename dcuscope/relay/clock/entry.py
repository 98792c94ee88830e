"""The ``clock`` entry every cross-node figure carries: what was subtracted from a node's
timestamps, why, and how far the result may be off.

    {"applied": "estimate"|"ptp"|"none"|"ignored"|..., "why": str,
     "correction_ns": offset subtracted at ``at_ns``, "uncertainty_ns": its bound there,
     "at_ns": the node timestamp it is evaluated at}

Live runs take it from :meth:`dcuscope.relay.live.state.RelayState.correction`; stored runs from the clock view
stored with the run (:func:`stored_run_correction`), the one :func:`dcuscope.relay.store.runs.load_runs` moved
their timestamps by.
"""

from __future__ import annotations

from dcuscope.relay.clock.correction import Correction, Segment, stored_correction


def clock_entry(corr: Correction, at_ns: int) -> dict:
    """The ``clock`` entry of a node whose timestamps ``corr`` moves, evaluated at node time ``at_ns``."""
    offset, bound = corr.at(at_ns)
    return {"applied": corr.applied, "why": corr.why, "correction_ns": offset, "uncertainty_ns": bound, "at_ns": at_ns}


def stored_run_correction(clock: object) -> Correction:
    """The correction a stored run's clock view says was applied (as :func:`dcuscope.relay.store.runs.load_runs`
    applies it), with its bound: ``correction_uncertainty_ns``, or for views stored before it
    existed the estimate's ``uncertainty_ns`` where the estimate was applied."""
    if not isinstance(clock, dict):
        return Correction("none", "no clock stored with the run")
    value, fault = stored_correction(clock)
    applied = str(clock.get("applied", "none")) if fault is None else "ignored"
    why = str(clock.get("why", "")) if fault is None else f"stored correction ignored: {fault}"
    bound = clock.get("correction_uncertainty_ns")
    if not _is_int(bound):
        bound = clock.get("uncertainty_ns") if applied == "estimate" else 0
    bound = abs(bound) if _is_int(bound) else 0
    if value == 0:
        return Correction(applied, why, (), bound)
    return Correction(applied, why, (Segment(from_ns=0, ref_ns=0, offset_ns=value, uncertainty_ns=bound),))


def _is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
