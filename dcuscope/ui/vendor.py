"""Copy the page's front-end packages from ``ui/node_modules`` into ``ui/static/vendor/``.

    npm ci --prefix dcuscope/ui             # installs the versions pinned in ui/package-lock.json
    python -m dcuscope.ui.vendor                     # copies what the page loads (add --npm to run npm ci first)

The page works without them (it then polls the HTTP API instead of using Socket.IO), so a
missing vendor folder degrades the page, it does not break it. Everything is served by the
relay itself: no CDN, the page works offline.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

UI = Path(__file__).resolve().parent
VENDOR = UI / "static" / "vendor"
# (package, file inside the package) -> name under ui/static/vendor/
FILES = {
    ("socket.io-client", "dist/socket.io.min.js"): "socket.io.min.js",
    ("socket.io-client", "dist/socket.io.min.js.map"): "socket.io.min.js.map",
}


def copy_vendor(node_modules: Path = UI / "node_modules", target: Path = VENDOR) -> list[Path]:
    """Copy the files the page needs; raises FileNotFoundError naming the first one missing."""
    missing = [node_modules / pkg / path for (pkg, path) in FILES if not (node_modules / pkg / path).is_file()]
    if missing:
        raise FileNotFoundError(f"{missing[0]} not found: run `npm ci --prefix {UI}` first")
    target.mkdir(parents=True, exist_ok=True)
    copied = []
    for (pkg, path), name in FILES.items():
        copied.append(Path(shutil.copyfile(node_modules / pkg / path, target / name)))
    return copied


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dcuscope.ui.vendor", description=__doc__.splitlines()[0])
    parser.add_argument("--npm", action="store_true", help="run `npm ci --prefix dcuscope/ui` first")
    args = parser.parse_args(argv)
    if args.npm:
        subprocess.run(["npm", "ci", "--prefix", str(UI), "--no-audit", "--no-fund"], check=True)
    try:
        for path in copy_vendor():
            print(path.relative_to(UI.parent))
    except FileNotFoundError as exc:
        print(f"ui.vendor: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
