"""A benchmark's in-process measurement run from several checkouts side by side, in turn: these
machines are shared and noisy, so only figures of one run are compared. The script runs itself
with ``--inner`` from each checkout (its code first on ``sys.path``) and prints its figures as JSON;
so a script imports this module in its outer run only, where no checkout's code runs."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def checkouts(parser: argparse.ArgumentParser, others: list[Path], holds: str) -> list[Path]:
    """This checkout, then ``others``; a folder without ``holds`` (a file of a checkout) is an error."""
    found = [HERE, *(c.resolve() for c in others)]
    for c in found[1:]:
        if not (c / holds).exists():
            parser.error(f"--checkout {c}: not a dcuscope checkout (no {holds})")
    return found


def alternate(script: str, inner: list[str], where: list[Path], rounds: int) -> list[list[dict]]:
    """``script --inner *inner`` from each checkout in turn, ``rounds`` times: each checkout's figures."""
    results: list[list[dict]] = [[] for _ in where]
    for _ in range(rounds):
        for c, got in zip(where, results):
            out = subprocess.run([sys.executable, script, "--inner", *inner], cwd=c, env=dict(os.environ, PYTHONPATH=str(c)),
                                 capture_output=True, text=True, check=False)
            if out.returncode != 0:
                sys.exit(f"{Path(script).name}: {c} failed: {out.stderr.strip().splitlines()[-1:]}")
            got.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return results
