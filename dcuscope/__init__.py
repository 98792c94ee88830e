"""The composition root: the ``dcuscope`` command line and the demo, which wire the pipeline
framework, the probes and the relay together. Nothing imports this package."""
