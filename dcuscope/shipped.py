"""The configurations dcuscope ships (``configs/*.yaml``, in the package once installed): found by
name (``dcuscope run vtest``) and listed (``dcuscope configs``), each with the first sentence of
its opening comment."""

from __future__ import annotations

import argparse
import re
import textwrap
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


def add_configs_parser(sub) -> None:
    p = sub.add_parser("configs", help="list the pipeline configurations dcuscope ships (dcuscope run NAME runs one)",
                       description="List the shipped pipeline configurations: `dcuscope run NAME` runs one as it "
                                   "is; --copy DIR writes them to DIR to start your own from (their clips and "
                                   "models are named by absolute path there).")
    p.add_argument("--copy", type=Path, metavar="DIR", help="copy them into DIR (made if missing; files there kept)")
    p.set_defaults(func=configs_command)


def configs_command(args: argparse.Namespace) -> int:
    configs = shipped()
    if args.copy is None:
        width = max(map(len, configs), default=0)
        for name, path in configs.items():
            lines = textwrap.wrap(summary(path), max(40, 100 - width - 2)) or [""]
            print(f"{name:<{width}}  {lines[0]}")
            for line in lines[1:]:
                print(f"{'':<{width}}  {line}")
        print(f"\n(in {CONFIGS}; run one with: dcuscope run NAME)")
        return 0
    if args.copy.exists() and not args.copy.is_dir():
        raise UsageError(f"--copy {args.copy}: not a folder")
    args.copy.mkdir(parents=True, exist_ok=True)
    for path in configs.values():
        out = args.copy / path.name
        if out.exists():
            print(f"{out}: exists, kept")
            continue
        # Paths relative to the shipped file (its clips, a model) made absolute, so that the copy runs anywhere.
        text = path.read_text(encoding="utf-8").replace("../assets/", f"{(DATA / 'assets').as_posix()}/")
        out.write_text(text, encoding="utf-8")
        print(f"{out}")
    return 0
