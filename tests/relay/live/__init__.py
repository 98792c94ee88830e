"""Tests of relay.live."""
