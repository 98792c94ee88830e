"""The credential a node presents to a relay, and where both look for it by default."""

TOKEN_ENV = "DCUSCOPE_TOKEN"
"""The environment variable a node's ``--token`` (and the relay's) defaults to: a secret given on a
command line is in every process listing."""
