"""The nodes' ingest WebSocket: hellos, batches, clock reports, ends."""
