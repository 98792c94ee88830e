"""Tests of probes.capture."""
