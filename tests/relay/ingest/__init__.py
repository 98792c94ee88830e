"""Tests of relay.ingest."""
