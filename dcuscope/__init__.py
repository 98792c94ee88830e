"""dcuscope: the one import name of the project.

Its own modules (``dcuscope.cli``, ``dcuscope.demo``, the commands) are the composition root: they
wire the pipeline framework, the probes and the relay together, and nothing else imports them. Its
subpackages (``core``, ``protocol``, ``model``, ``plugins``, ``pipeline``, ``probes``, ``relay``, ``ui``) are
folders of this one, in a checkout as installed; the repository's top-level ``core/`` … ``ui/``
are links to them, so that the paths the docs name hold in a checkout.
"""
