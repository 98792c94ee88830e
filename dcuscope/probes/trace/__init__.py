"""Trace files and what reads them on the node: writing and reading a run's file, following one
being written, ``dcuscope stats``'s document and the exports (Perfetto, CSV). The events are
:mod:`dcuscope.protocol.events`, their delays :mod:`dcuscope.model`.

Imports nothing of probes (``core``, ``protocol`` and ``model`` only).
"""
