"""Rollups: per DCU, stage and minute (and hour), mergeable sketches of delay, service and wait, kept long after the raw
events; the store writes them (relay.store.compaction) and answers from them (relay.store.history)."""
