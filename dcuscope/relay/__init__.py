"""The monitoring host: ingest of probe events from nodes, clock offsets, live delays, storage, API.

Run it with ``dcuscope relay`` (or ``python -m dcuscope.relay``); nodes ship to it with
:class:`dcuscope.probes.ship.relayexport.RelayExporter`.
"""
