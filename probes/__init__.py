"""Pad-probe tracepoints on every element, the event buffer, trace files, statistics, exports."""
