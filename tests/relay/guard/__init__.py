"""Tests of relay.guard."""
