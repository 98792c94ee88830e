"""The delay model: what the events of a run mean, computed alike by a node (``dcuscope stats``,
``compare``) and by the relay.

- :mod:`.frametable`: a run's events paired into one row per frame;
- :mod:`.delays`: per-stage and per-frame delays (wait, service, end to end), statistics, the
  bottleneck; :mod:`.facts`: the run's accounting (drops, losses, facts);
- :mod:`.compare` and :mod:`.bootstrap`: two runs compared, with resampled intervals.

Imports ``core`` and ``protocol`` only.
"""
