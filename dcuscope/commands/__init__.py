"""The ``dcuscope`` commands, one module each: its options (``add_..._parser``) and what runs it.
``dcuscope/cli.py`` puts them together; what several share is :mod:`.options`. Heavy modules
(GStreamer, aiohttp, numpy) load inside a command, never at the command line's start.

The relay's command is :mod:`dcuscope.relay.commands` (``python -m dcuscope.relay`` too), capacity's
:mod:`dcuscope.capacity.command`.
"""
