"""Where dcuscope's data is: ``assets/`` (the models and clips, with their notes) and ``configs/``,
at the top of a checkout, in the package once installed (``setup.py``)."""

from pathlib import Path

_package = Path(__file__).resolve().parents[1]
DATA = _package if (_package / "configs").is_dir() else _package.parent
"""The folder that holds ``assets/`` and ``configs/``: the package installed, else the checkout."""
