"""Tests of probes.clocks."""
