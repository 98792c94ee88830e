"""The configurations dcuscope ships (``configs/*.yaml``, in the package once installed): found by
name (``dcuscope run vtest``) and listed (``dcuscope configs``), each with the first sentence of
its opening comment."""

from __future__ import annotations

import re
from pathlib import Path

from dcuscope.core.datadir import DATA
from dcuscope.core.errors import UsageError

CONFIGS = DATA / "configs"


def shipped() -> dict[str, Path]:
    """Name -> file of every shipped pipeline configuration."""
    return {p.stem: p for p in sorted(CONFIGS.glob("*.yaml"))}


def resolve(config: Path) -> Path:
    """``config`` itself where it exists or names a path; a shipped configuration's file where it is
    one's name (``vtest`` or ``vtest.yaml``); UsageError for a name that is neither."""
    configs = shipped()
    if config.exists():
        return config
    if len(config.parts) > 1:
        name = config.name.removesuffix(".yaml")
        if name in configs:  # configs/quad.yaml outside a checkout: the shipped one is there by name
            raise UsageError(f"{config}: no such configuration file; the shipped one of that name runs with: "
                             f"dcuscope run {name}")
        return config
    if config.name.removesuffix(".yaml") in configs:
        return configs[config.name.removesuffix(".yaml")]
    raise UsageError(f"{config}: no such configuration file, nor a shipped configuration "
                     f"({', '.join(configs)}: dcuscope configs says what each runs)")


_SENTENCE_END = re.compile(r"(?<=[.!?])\s+(?=[A-Z(])")


def summary(path: Path) -> str:
    """The first sentence of a configuration's opening comment (what it runs), whole: the comment's
    prose lines up to the first indented one (a command line), joined."""
    prose = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#") or line.startswith("#  "):
            break
        prose.append(line.removeprefix("#").strip())
    return _SENTENCE_END.split(" ".join(prose), maxsplit=1)[0]
