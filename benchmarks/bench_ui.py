"""The page under load: drawing rate and memory of the UI in headless Chromium, for minutes.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_ui.py [--minutes 5] [--nodes 2] [--sources 6] [--fps 60] [--quick]

A relay (``python -m relay``) is fed by simulated nodes (``probes.simnode --paced``: every event
shipped when its time comes), by default 2 DCUs x 6 sources x 60 fps = 720 frames/s, 8,640
events/s. The page follows live, alternating stage view and frame view every sample period.
Measured per period: requestAnimationFrame rate (an rAF counter of the benchmark's own, beside
the page's), the page's drawing time per frame, bars drawn, JS heap after a forced GC
(``--enable-precise-memory-info --js-flags=--expose-gc``) and DOM nodes. It passes when every
period draws at >= 30 frames/s and the heap at the end is within 16 MiB of the heap after warm-up.

Every simulated node connects from 127.0.0.1, so the relay is started as bench_relay.py starts
it, with its per-address connection cap raised (else 16 nodes leave the browser no connection).
Without Chromium or Playwright, or when the page does not load, it says so in one line and
exits with status 2.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_relay import Relay  # noqa: E402
from benchmarks.figures import CannotRun, dumps, fmt, maximum, mean, minimum, missing, one_line, ratio, run  # noqa: E402
from tests.ui.helpers import CHROMIUM, launch_chromium, sim_nodes  # noqa: E402

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


def summarise(samples: list[dict], errors: list[str]) -> dict:
    """The run's figures from the samples (the first one taken after warm-up, the rest per period)."""
    measured = samples[1:]
    none = "no sample period was measured"
    heap0, heap1 = samples[0]["heap"] / 2**20, samples[-1]["heap"] / 2**20
    return {
        "min_fps": minimum([s["fps"] for s in measured], none), "mean_fps": mean([s["fps"] for s in measured], none),
        "max_draw_ms_mean": maximum([s["perf"]["drawMsMean"] for s in measured], none),
        "heap_start_mib": heap0, "heap_end_mib": heap1, "heap_max_mib": max(s["heap"] for s in samples) / 2**20,
        "dom_start": samples[0]["dom"], "dom_end": samples[-1]["dom"],
        "frames_per_s_in": mean([s["in_fps"] for s in measured], none), "page_errors": errors,
    }


def watch(playwright, url: str, args: argparse.Namespace, errors: list[str]) -> list[dict]:
    """The page at ``url`` in headless Chromium: a sample after warm-up, then one per period
    (printed as they come); the page's errors are added to ``errors``."""
    browser = launch_chromium(playwright, ["--enable-precise-memory-info", "--js-flags=--expose-gc"])
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(url + "/")
    # the page's modules are loaded (on a busy machine that can take longer than the warm-up)
    page.wait_for_function("() => window.dcuscope !== undefined", timeout=60_000)
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
        s["fps"] = ratio(s["raf"] - prev["raf"], dt, "no time passed in the period")
        s["in_fps"] = ratio(s["received"] - prev["received"], dt, "no time passed in the period")
        samples.append(s)
        print(f"{(s['t'] - samples[0]['t']) / 1000:6.0f} {s['tab']:>5} {fmt(s['fps'], '6.1f')}"
              f" {fmt(s['perf']['drawMsMean'], '8.2f')} {fmt(s['perf']['drawMsMax'], '7.1f')}"
              f" {s['bars']:6d} {fmt(s['in_fps'], '11.0f')} {s['heap'] / 2**20:9.1f} {s['dom']:5d}", flush=True)
    browser.close()
    return samples


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=5.0, help="measured time (after warm-up)")
    parser.add_argument("--nodes", type=int, default=2)
    parser.add_argument("--sources", type=int, default=6)
    parser.add_argument("--fps", type=float, default=60.0, help="frames per second per source")
    parser.add_argument("--warmup", type=float, default=20.0, help="seconds before the first sample")
    parser.add_argument("--period", type=float, default=10.0, help="seconds per sample")
    parser.add_argument("--json", type=Path, help="write the samples and summary here")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: 1 node x 2 sources x 30 fps, 3 s warm-up, two 2 s periods")
    args = parser.parse_args(argv)
    if args.quick:
        args.nodes, args.sources, args.fps, args.warmup, args.period = 1, 2, 30.0, 3.0, 2.0
        args.minutes = 2 * args.period / 60
    if args.nodes < 1 or args.sources < 1 or args.fps <= 0 or args.period <= 0 or args.minutes <= 0:
        parser.error("--nodes, --sources, --fps, --period and --minutes must be positive")

    try:
        from playwright.sync_api import Error as PlaywrightError
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        raise CannotRun(f"Playwright is not installed ({exc})") from exc
    if not Path(CHROMIUM).exists():
        raise CannotRun(f"{CHROMIUM} not found: install Debian's chromium package")

    names = [f"DCU-{k + 1}" for k in range(args.nodes)]
    seconds = args.warmup + args.minutes * 60 + 5
    errors: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-ui-") as tmp_name:
        tmp = Path(tmp_name)
        relay = Relay(tmp / "relay.db")
        feeder = sim_nodes(relay.url, tmp, names, frames=int(args.fps * seconds), sources=args.sources, fps=args.fps,
                           paced=True)
        try:
            with sync_playwright() as playwright:
                samples = watch(playwright, relay.url, args, errors)
        except PlaywrightError as exc:
            raise CannotRun(f"Chromium failed: {one_line(exc.message)}") from exc
        finally:
            feeder.stop()
            relay.stop()

    summary = summarise(samples, errors)
    heap0, heap1 = summary["heap_start_mib"], summary["heap_end_mib"]
    fast = not missing(summary["min_fps"]) and summary["min_fps"] >= MIN_FPS
    ok = fast and heap1 - heap0 <= HEAP_SLACK_MB and not errors
    print(dumps(summary, indent=1))
    print(f"{'PASS' if ok else 'FAIL'}: rAF >= {MIN_FPS:g}/s in every period: {fmt(summary['min_fps'], '.1f')}; "
          f"heap {heap0:.1f} -> {heap1:.1f} MiB (bound +{HEAP_SLACK_MB:g})")
    if args.json:
        args.json.write_text(dumps({"samples": samples, "summary": summary}, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(run(main))
