"""The page under load: drawing rate and memory of the UI in headless Chromium, for minutes.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_ui.py [--minutes 5] [--nodes 2] [--sources 6] [--fps 60]

A relay (``python -m relay``) is fed by simulated nodes (``probes.simnode --paced``: every event
shipped when its time comes), by default 2 DCUs x 6 sources x 60 fps = 720 frames/s, 8,640
events/s. The page follows live, alternating stage view and frame view every sample period.
Measured per period: requestAnimationFrame rate (an rAF counter of the benchmark's own, beside
the page's), the page's drawing time per frame, bars drawn, JS heap after a forced GC
(``--enable-precise-memory-info --js-flags=--expose-gc``) and DOM nodes. It passes when every
period draws at >= 30 frames/s and the heap at the end is within 16 MiB of the heap after warm-up.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.ui.helpers import env, launch_chromium, sim_nodes  # noqa: E402

MIN_FPS = 30.0
HEAP_SLACK_MB = 16.0
RAF_COUNTER = """() => {
    window.__bench = {frames: 0};
    const tick = () => { window.__bench.frames++; requestAnimationFrame(tick); };
    requestAnimationFrame(tick);
}"""
SAMPLE = """() => {
    if (window.gc) window.gc();
    const d = window.dcuscope.debug();
    const bars = d.tab === "stage"
        ? Object.values(d.stage.bars).reduce((a, b) => a + Object.values(b).reduce((x, y) => x + y, 0), 0)
        : Object.values(d.frame.nodes ?? {}).reduce((a, b) => a + b.shown, 0);
    return {t: performance.now(), raf: window.__bench.frames, heap: performance.memory.usedJSHeapSize,
            dom: document.getElementsByTagName("*").length, perf: window.dcuscope.perf(5000), bars, tab: d.tab,
            runs: d.stage.runs, received: Object.values(d.stores).reduce((a, s) => a + s.received, 0)};
}"""


def start_relay(db: Path) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "relay", "--port", "0", "--db", str(db)], cwd=ROOT, env=env(),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    line = proc.stdout.readline()
    m = re.search(r"http://127\.0\.0\.1:(\d+)", line)
    if not m:
        proc.kill()
        raise SystemExit(f"relay did not start: {line!r}")
    return proc, f"http://127.0.0.1:{m.group(1)}"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=5.0, help="measured time (after warm-up)")
    parser.add_argument("--nodes", type=int, default=2)
    parser.add_argument("--sources", type=int, default=6)
    parser.add_argument("--fps", type=float, default=60.0, help="frames per second per source")
    parser.add_argument("--warmup", type=float, default=20.0, help="seconds before the first sample")
    parser.add_argument("--period", type=float, default=10.0, help="seconds per sample")
    parser.add_argument("--json", type=Path, help="write the samples and summary here")
    args = parser.parse_args()

    from playwright.sync_api import sync_playwright

    names = [f"DCU-{k + 1}" for k in range(args.nodes)]
    seconds = args.warmup + args.minutes * 60 + 5
    with tempfile.TemporaryDirectory(prefix="bench-ui-") as tmp_name:
        tmp = Path(tmp_name)
        relay, url = start_relay(tmp / "relay.db")
        feeder = sim_nodes(url, tmp, names, frames=int(args.fps * seconds), sources=args.sources, fps=args.fps,
                           paced=True)
        try:
            with sync_playwright() as playwright:
                browser = launch_chromium(playwright, ["--enable-precise-memory-info", "--js-flags=--expose-gc"])
                page = browser.new_page(viewport={"width": 1600, "height": 1000})
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url + "/")
                page.evaluate(RAF_COUNTER)
                print(f"load: {args.nodes} nodes x {args.sources} sources x {args.fps:g} fps = "
                      f"{args.nodes * args.sources * args.fps:g} frames/s; warm-up {args.warmup:g} s", flush=True)
                page.wait_for_timeout(args.warmup * 1000)
                samples = [page.evaluate(SAMPLE)]
                print(f"{'t s':>6} {'view':>5} {'rAF/s':>6} {'draw ms':>8} {'max ms':>7} {'bars':>6}"
                      f" {'frames/s in':>11} {'heap MiB':>9} {'DOM':>5}", flush=True)
                tabs = ["stage", "frame"]
                for k in range(max(1, round(args.minutes * 60 / args.period))):
                    page.click(f".tab[data-tab={tabs[k % 2]}]")
                    page.wait_for_timeout(args.period * 1000)
                    s = page.evaluate(SAMPLE)
                    prev = samples[-1]
                    dt = (s["t"] - prev["t"]) / 1000
                    s["fps"] = (s["raf"] - prev["raf"]) / dt
                    s["in_fps"] = (s["received"] - prev["received"]) / dt
                    samples.append(s)
                    print(f"{(s['t'] - samples[0]['t']) / 1000:6.0f} {s['tab']:>5} {s['fps']:6.1f}"
                          f" {s['perf']['drawMsMean']:8.2f} {s['perf']['drawMsMax']:7.1f} {s['bars']:6d}"
                          f" {s['in_fps']:11.0f} {s['heap'] / 2**20:9.1f} {s['dom']:5d}", flush=True)
                browser.close()
        finally:
            feeder.stop()
            relay.terminate()
            relay.wait(15)

    measured = samples[1:]
    heap0, heap1 = samples[0]["heap"] / 2**20, samples[-1]["heap"] / 2**20
    summary = {
        "min_fps": min(s["fps"] for s in measured), "mean_fps": sum(s["fps"] for s in measured) / len(measured),
        "max_draw_ms_mean": max(s["perf"]["drawMsMean"] for s in measured),
        "heap_start_mib": heap0, "heap_end_mib": heap1, "heap_max_mib": max(s["heap"] for s in samples) / 2**20,
        "dom_start": samples[0]["dom"], "dom_end": samples[-1]["dom"],
        "frames_per_s_in": sum(s["in_fps"] for s in measured) / len(measured), "page_errors": errors,
    }
    ok = summary["min_fps"] >= MIN_FPS and heap1 - heap0 <= HEAP_SLACK_MB and not errors
    print(json.dumps(summary, indent=1))
    print(f"{'PASS' if ok else 'FAIL'}: rAF >= {MIN_FPS:g}/s in every period: {summary['min_fps']:.1f}; "
          f"heap {heap0:.1f} -> {heap1:.1f} MiB (bound +{HEAP_SLACK_MB:g})")
    if args.json:
        args.json.write_text(json.dumps({"samples": samples, "summary": summary}, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
