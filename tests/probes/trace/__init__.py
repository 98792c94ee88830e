"""Tests of probes.trace."""
