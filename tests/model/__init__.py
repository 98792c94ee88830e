"""Tests of dcuscope.model: the delay model."""
