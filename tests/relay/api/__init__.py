"""Tests of relay.api."""
