"""The contract between nodes and relays: what both sides speak, in one place both import.

- :mod:`.events`: the event record (``EVENT_DTYPE``), its points, drop reasons and facts, the
  run's :class:`~.events.TraceHeader`;
- :mod:`.wire`: binary batches and the JSON messages (``hello``, ``clock``, ``end``), the protocol's
  version and limits; :mod:`.envelope`: the ingest WebSocket's messages around them;
- :mod:`.clockdatagram`: the UDP clock exchange's datagrams and the offer in a hello reply;
- :mod:`.ptptrust`: what a node's PTP report is worth; :mod:`.credentials`: where the node token
  is looked for;
- :mod:`.errors`: a malformed payload (:class:`~.errors.ProtocolError`) and one beyond a relay's
  limit (:class:`~.errors.LimitExceeded`).

Imports ``core`` only: the node (``probes``) and the relay import it, it imports neither.
"""
