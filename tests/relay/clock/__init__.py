"""Tests of relay.clock."""
