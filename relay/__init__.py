"""The monitoring host: ingest of probe events from nodes, clock offsets, live delays, storage, API.

Run it with ``dcuscope relay`` (or ``python -m relay``); nodes ship to it with
:class:`probes.ship.relayexport.RelayExporter`.
"""
