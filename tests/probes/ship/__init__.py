"""Tests of probes.ship."""
