"""Each element of a traced gst-launch app: dcuscope's median delay (``dcuscope stats``) beside GStreamer's
own ``latency`` tracer's (flags=element, from the same run's GST_DEBUG log), within 0.1 ms + 3 %.

    python scripts/platforms/latency_table.py TRACE LATENCY_LOG TABLE_OUT

Writes the table to TABLE_OUT, prints a one-line summary; exit 1 when an element is outside the bound
or fewer than 4 elements could be compared (scripts/platforms.sh, bullseye).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np


def main(trace: str, log: str, table_out: str) -> int:
    out = subprocess.run([sys.executable, "-m", "dcuscope.cli", "stats", trace, "--json"], capture_output=True, text=True)
    if out.returncode != 0:
        print(f"dcuscope stats failed: {out.stderr.strip()}")
        return 1
    (node,) = json.loads(out.stdout)["nodes"].values()
    text = Path(log).read_text(errors="replace")
    rows, bad = [], []
    for stage, ours in node["stages"].items():
        theirs = [int(t) / 1e6 for t in re.findall(
            rf"element-latency, element-id=\(string\)\S+, element=\(string\){re.escape(stage)}, src=\(string\)\w+, "
            r"time=\(g?u?int64\)(\d+)", text)]
        if not theirs:
            continue
        median = float(np.median(theirs))
        diff = ours["p50_ms"] - median
        ok = abs(diff) <= 0.1 + 0.03 * median
        rows.append(f"{stage:<14} {ours['p50_ms']:10.3f} {median:10.3f} {diff:+9.3f}  {'ok' if ok else 'OUTSIDE'}")
        if not ok:
            bad.append(stage)
    head = f"{'element':<14} {'dcuscope':>10} {'latency':>10} {'diff':>9}  (median ms, {node['frames']['complete']} frames)"
    Path(table_out).write_text("\n".join([head, *rows]) + "\n")
    if bad or len(rows) < 4:
        print(f"elements outside 0.1 ms + 3 % of the latency tracer: {', '.join(bad) or 'none'}; "
              f"{len(rows)} compared")
        return 1
    print(f"{len(rows)} elements within 0.1 ms + 3 % of the latency tracer")
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
