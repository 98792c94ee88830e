"""dcuscope: the one import name of the project.

Its own modules (``dcuscope.cli``, ``dcuscope.demo``, the commands) are the composition root: they
wire the pipeline framework, the probes and the relay together, and nothing else imports them. Its
subpackages are the repository's top-level folders (``core/``, ``plugins/``, ``pipeline/``,
``probes/``, ``relay/``, ``ui/``): installed, the build puts them under ``dcuscope/`` (``setup.py``);
in a checkout, the folder above this one is searched as well, so that ``dcuscope.relay`` is
``relay/`` there too (with or without an editable install, and for GStreamer's own Python, which
loads the elements of ``plugins/loader/python/``).
"""

from pathlib import Path as _Path

SUBPACKAGES = ("core", "plugins", "pipeline", "probes", "relay", "ui")
"""The repository's folders that are ``dcuscope.*`` once installed."""

_here = _Path(__file__).resolve().parent
_checkout = _here.parent
CHECKOUT = not (_here / "relay").is_dir() and (_checkout / "relay" / "__init__.py").is_file()
"""Whether this is a checkout of the repository (else an installed package)."""
if CHECKOUT:
    __path__.append(str(_checkout))  # noqa: F821 - a package's __path__
DATA = _checkout if CHECKOUT else _here
"""The folder that holds ``assets/`` (models, clips) and ``configs/``: the checkout, or the package."""
