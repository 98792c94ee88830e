"""Tests of relay.rollup."""
