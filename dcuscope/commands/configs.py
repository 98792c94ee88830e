"""``dcuscope configs``: the pipeline configurations dcuscope ships (:mod:`dcuscope.shipped`), listed
or copied to start one's own from."""

from __future__ import annotations

import argparse
import textwrap
from pathlib import Path

from dcuscope.core.datadir import DATA
from dcuscope.core.errors import UsageError
from dcuscope.shipped import CONFIGS, shipped, summary


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
