"""Tests of dcuscope.protocol: what nodes and relays speak."""
