"""The page under load: drawing rate and memory of the UI in headless Chromium, for minutes.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_ui.py [--minutes 5] [--nodes 2] [--sources 6] [--fps 60] [--quick]
    PYTHONPATH=. .venv/bin/python benchmarks/bench_ui.py --fleet --nodes 64 --sources 4 --fps 30 [--minutes 5] [--open-minutes 1]
    PYTHONPATH=. .venv/bin/python benchmarks/bench_ui.py --follow-cpu [--nodes 2 --sources 3 --fps 30 --period 20]

A relay (``python -m dcuscope.relay``) is fed by simulated nodes (``probes.ship.simnode --paced``: every event
shipped when its time comes), by default 2 DCUs x 6 sources x 60 fps = 720 frames/s, 8,640
events/s. Measured per period: requestAnimationFrame rate (an rAF counter of the benchmark's own,
beside the page's), the page's drawing time per frame, bars drawn, JS heap after a forced GC
(``--enable-precise-memory-info --js-flags=--expose-gc``) and DOM nodes.

Without ``--fleet`` the page shows every DCU (``?open=*``: what the page drew before the fleet
overview, whatever their number) and follows live, alternating stage view and frame view every
sample period. It passes when every period draws at >= 30 frames/s and the heap at the end is
within 16 MiB of the heap after warm-up.

With ``--fleet`` the page is measured in three states in turn, on the same relay and DCUs, and
the states are printed side by side, with the WebSocket bytes the relay pushed to the page and
the CPU used by Chromium, by the relay and the nodes, and by the whole machine (a machine the load
saturates starves Chromium's frames whatever the page does: these tell which it was):

- ``overview``: the page as it opens on the fleet (``?open=`` with 4 DCUs or fewer, which it
  would open whole): the overview's rows, no DCU opened, for ``--minutes``, the heap sampled
  every ``--heap-period`` (30 s) and its series and slope printed. It passes at >= 30 frames/s in
  every period, a heap of at most 300 MiB, and a flat heap: its slope times the run's length
  within 16 MiB.
- ``one``: a click on the overview's first row of a DCU that is up (the worst) opens it; measured for
  ``--open-minutes`` as the page without ``--fleet`` is (stage and frame views in turn), it
  passes as that does: >= 30 frames/s in every period.
- ``all``: a fresh page on ``?open=*``, every DCU drawn as before the overview, for
  ``--open-minutes``: reported beside the others, no verdict (``--no-all`` leaves it out).

With ``--follow-cpu`` the page follows every DCU live in the stage view, redrawing every animation
frame (the page before its redraws were capped: ``dcuscope.setFollowRedrawMs(0)``) and then as it
does (at most every FOLLOW_REDRAW_MS of ui/static/app.js), ``--period`` s each after ``--warmup``
s, on one page; it prints the draws/s and the CPU Chromium used in each (cores, and the renderer's
and GPU process's shares) side by side. It passes when the page draws at >= 10/s as it does.

Every simulated node connects from 127.0.0.1, so the relay is started as bench_relay.py starts
it, with its per-address connection cap raised (else 16 nodes leave the browser no connection).
Without Chromium or Playwright, or when the page does not load, it says so in one line and
exits with status 2.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the project importable
    sys.path.insert(0, str(ROOT))

from benchmarks.bench_relay import Relay  # noqa: E402
from benchmarks.figures import (NA, CannotRun, Figure, dumps, fmt, maximum, mean, minimum, missing,  # noqa: E402
                               one_line, ratio, run)
from tests.ui.helpers import CHROMIUM, launch_chromium, sim_nodes  # noqa: E402

AUTO_OPEN_MAX = 4
"""ui/static/overview.js: the page opens a fleet of at most this many DCUs whole by itself."""

MIN_FPS = 30.0
HEAP_SLACK_MB = 16.0
FLEET_HEAP_MAX_MB = 300.0
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
            runs: d.stage.runs, received: Object.values(d.stores).reduce((a, s) => a + s.received, 0),
            rows: d.overview.total, stores: Object.keys(d.stores).length};
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


class CpuMeter:
    """CPU seconds used so far by Chromium (this process's descendants named chrom*: the page and its
    browser), by the load (the relay and the simulated nodes: the other descendants), and by the
    whole machine, from /proc (Linux). On a machine the load saturates, Chromium's frame rate tells
    of the machine as much as of the page: these say which."""

    def __init__(self) -> None:
        self.tick = os.sysconf("SC_CLK_TCK")

    def descendants(self) -> dict[int, str]:
        parent, comm = {}, {}
        for entry in os.listdir("/proc"):
            if not entry.isdigit():
                continue
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            name, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:].split()
            parent[int(entry)], comm[int(entry)] = int(rest[1]), name
        mine, frontier = {}, {os.getpid()}
        while frontier:
            frontier = {pid for pid, ppid in parent.items() if ppid in frontier and pid not in mine}
            mine.update({pid: comm[pid] for pid in frontier})
        return mine

    def cpu_s(self, pid: int) -> float:
        try:
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            return 0.0
        return (int(fields[11]) + int(fields[12])) / self.tick

    def snapshot(self) -> dict:
        """{"chromium", "load", "busy", "total"}: CPU seconds (busy and total: the machine's, all cores)."""
        if not Path("/proc/stat").exists():
            return {}
        browser = load = 0.0
        for pid, name in self.descendants().items():
            if name.startswith(("chrom", "headless")):
                browser += self.cpu_s(pid)
            elif name.startswith("python"):
                load += self.cpu_s(pid)
        cpu = [int(v) for v in Path("/proc/stat").read_text().splitlines()[0].split()[1:]]
        idle = cpu[3] + cpu[4]
        return {"chromium": browser, "load": load, "busy": (sum(cpu) - idle) / self.tick, "total": sum(cpu) / self.tick}


def chromium_cpu_s(cpu: "CpuMeter") -> dict[str, float]:
    """CPU seconds used so far by each kind of Chromium process (``--type=``: renderer, gpu-process,
    utility; the browser itself without one), summed."""
    out: dict[str, float] = {}
    for pid, name in cpu.descendants().items():
        if not name.startswith(("chrom", "headless")):
            continue
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        kind = next((w[len("--type="):] for w in cmdline.split() if w.startswith("--type=")), "browser")
        out[kind] = out.get(kind, 0.0) + cpu.cpu_s(pid)
    return out


def cpu_rates(now: dict, before: dict, dt: float) -> dict:
    """Cores used over ``dt`` s by Chromium and by the load, and the machine's busy share (%)."""
    if not now or not before or dt <= 0:
        none = NA("no /proc to read CPU times from")
        return {"chromium_cores": none, "load_cores": none, "machine_busy_pct": none}
    return {"chromium_cores": (now["chromium"] - before["chromium"]) / dt,
            "load_cores": (now["load"] - before["load"]) / dt,
            "machine_busy_pct": ratio(100 * (now["busy"] - before["busy"]), now["total"] - before["total"], "no CPU time")}


class Traffic:
    """Bytes the relay pushed to the page over its WebSocket (Socket.IO frames), counted as they come."""

    def __init__(self, page) -> None:
        self.bytes = 0
        page.on("websocket", lambda ws: ws.on("framereceived", self.received))

    def received(self, payload) -> None:
        self.bytes += len(payload.encode() if isinstance(payload, str) else payload)


def open_page(browser, url: str, errors: list[str]):
    """A page on ``url`` with the benchmark's rAF counter, once the page's modules are loaded."""
    page = browser.new_page(viewport={"width": 1600, "height": 1000})
    page.on("pageerror", lambda e: errors.append(str(e)))
    traffic = Traffic(page)
    page.goto(url)
    # the page's modules are loaded (on a busy machine that can take longer than the warm-up)
    page.wait_for_function("() => window.dcuscope !== undefined", timeout=60_000)
    page.evaluate(RAF_COUNTER)
    return page, traffic


HEADER = (f"{'t s':>6} {'view':>5} {'rAF/s':>6} {'draw ms':>8} {'max ms':>7} {'bars':>6}"
          f" {'frames/s in':>11} {'heap MiB':>9} {'DOM':>5}")


def measure(page, periods: int, period: float, samples: list[dict], traffic: Traffic | None = None,
            label: str = "", cpu: CpuMeter | None = None) -> list[dict]:
    """``periods`` sample periods of ``period`` s after ``samples[-1]``, the stage and frame views
    taking turns; each sample printed as it comes (with ``label``, the WebSocket's kB/s and the CPU
    used when ``traffic`` and ``cpu`` are given)."""
    tabs = ["stage", "frame"]
    t0 = samples[0]["t"]
    for k in range(periods):
        page.click(f".tab[data-tab={tabs[k % 2]}]")
        page.wait_for_timeout(period * 1000)
        s = page.evaluate(SAMPLE)
        prev = samples[-1]
        dt = (s["t"] - prev["t"]) / 1000
        s["fps"] = ratio(s["raf"] - prev["raf"], dt, "no time passed in the period")
        s["in_fps"] = ratio(s["received"] - prev["received"], dt, "no time passed in the period")
        extra = ""
        if traffic is not None:
            s["ws_bytes"] = traffic.bytes
            s["ws_kbps"] = ratio(s["ws_bytes"] - prev["ws_bytes"], dt * 1000, "no time passed in the period")
            extra = f" {label:>8} {fmt(s['ws_kbps'], '8.1f')}"
        if cpu is not None:
            s["cpu"] = cpu.snapshot()
            s.update(cpu_rates(s["cpu"], prev.get("cpu", {}), dt))
            extra += (f" {fmt(s['chromium_cores'], '8.2f')} {fmt(s['load_cores'], '7.2f')}"
                      f" {fmt(s['machine_busy_pct'], '6.0f')}")
        samples.append(s)
        print(f"{(s['t'] - t0) / 1000:6.0f} {s['tab']:>5} {fmt(s['fps'], '6.1f')}"
              f" {fmt(s['perf']['drawMsMean'], '8.2f')} {fmt(s['perf']['drawMsMax'], '7.1f')}"
              f" {s['bars']:6d} {fmt(s['in_fps'], '11.0f')} {s['heap'] / 2**20:9.1f} {s['dom']:5d}{extra}", flush=True)
    return samples


def watch(playwright, url: str, args: argparse.Namespace, errors: list[str]) -> list[dict]:
    """The page at ``url`` in headless Chromium: a sample after warm-up, then one per period
    (printed as they come); the page's errors are added to ``errors``."""
    browser = launch_chromium(playwright, ["--enable-precise-memory-info", "--js-flags=--expose-gc"])
    page, _ = open_page(browser, url + "/?open=*", errors)
    print(f"load: {args.nodes} nodes x {args.sources} sources x {args.fps:g} fps = "
          f"{args.nodes * args.sources * args.fps:g} frames/s; warm-up {args.warmup:g} s", flush=True)
    page.wait_for_timeout(args.warmup * 1000)
    samples = [page.evaluate(SAMPLE)]
    print(HEADER, flush=True)
    measure(page, max(1, round(args.minutes * 60 / args.period)), args.period, samples)
    browser.close()
    return samples


# --- --follow-cpu: the page following live, redrawn every animation frame and capped ----------------

FOLLOW_MIN_DRAWS = 10.0
"""A page following live draws at least this often (draws/s) to look live (tests/ui/test_browser.py too)."""
FOLLOW_MODES = [("every frame", 0), ("capped", None)]
"""The redraw modes measured: a name and setFollowRedrawMs's argument (None: the page's own)."""


def follow_state(page, cpu: CpuMeter, seconds: float) -> dict:
    """Draws/s and cores of Chromium (all, renderer, GPU process) over ``seconds`` s of ``page``."""
    draws0, k0, t0 = page.evaluate("() => window.dcuscope.debug().draws"), chromium_cpu_s(cpu), time.monotonic()
    page.wait_for_timeout(seconds * 1000)
    draws1, k1, t1 = page.evaluate("() => window.dcuscope.debug().draws"), chromium_cpu_s(cpu), time.monotonic()
    dt = t1 - t0
    used = {k: v - k0.get(k, 0.0) for k, v in k1.items()}
    return {"seconds": dt, "draws_per_s": (draws1 - draws0) / dt, "chromium_cores": sum(used.values()) / dt,
            "renderer_cores": used.get("renderer", 0.0) / dt, "gpu_cores": used.get("gpu-process", 0.0) / dt}


FOLLOW_ROWS = [("draws/s", "draws_per_s", ".1f"), ("Chromium CPU, cores", "chromium_cores", ".2f"),
               ("  renderer", "renderer_cores", ".2f"), ("  GPU process", "gpu_cores", ".2f")]


def follow_table(states: dict[str, dict]) -> list[str]:
    """The states side by side, one line per figure."""
    width = max(len(r[0]) for r in FOLLOW_ROWS)
    lines = [f"{'':{width}} " + " ".join(f"{name:>12}" for name in states)]
    for label, key, spec in FOLLOW_ROWS:
        lines.append(f"{label:{width}} " + " ".join(f"{fmt(st[key], spec):>12}" for st in states.values()))
    return lines


def follow_cpu(playwright, url: str, args: argparse.Namespace, errors: list[str]) -> dict[str, dict]:
    """The page following every DCU in each FOLLOW_MODES mode in turn (the module's docstring)."""
    browser = launch_chromium(playwright)
    page, _ = open_page(browser, url + "/?open=*", errors)
    print(f"load: {args.nodes} nodes x {args.sources} sources x {args.fps:g} fps = "
          f"{args.nodes * args.sources * args.fps:g} frames/s; warm-up {args.warmup:g} s, {args.period:g} s a mode",
          flush=True)
    page.wait_for_function("(n) => Object.values(window.dcuscope.debug().stores).filter((s) => s.received > 0)"
                           ".length >= n", arg=args.nodes, timeout=120_000)
    page.wait_for_timeout(args.warmup * 1000)
    cpu, states = CpuMeter(), {}
    default = page.evaluate("() => window.dcuscope.debug().followRedrawMs")
    for name, ms in FOLLOW_MODES:
        page.evaluate("(ms) => window.dcuscope.setFollowRedrawMs(ms)", default if ms is None else ms)
        page.wait_for_timeout(1000)
        states[name] = follow_state(page, cpu, args.period)
        print(f"{name}: {states[name]['draws_per_s']:.1f} draws/s, {states[name]['chromium_cores']:.2f} cores", flush=True)
    browser.close()
    return states


def report_follow(states: dict[str, dict], errors: list[str]) -> int:
    for line in follow_table(states):
        print(line)
    capped, every = states["capped"], states["every frame"]
    saved = 1 - capped["chromium_cores"] / every["chromium_cores"] if every["chromium_cores"] > 0 else float("nan")
    ok = capped["draws_per_s"] >= FOLLOW_MIN_DRAWS and not errors
    print(f"{'PASS' if ok else 'FAIL'}: capped draws >= {FOLLOW_MIN_DRAWS:g}/s: {capped['draws_per_s']:.1f}; "
          f"Chromium CPU {every['chromium_cores']:.2f} -> {capped['chromium_cores']:.2f} cores ({100 * saved:.0f} % less)"
          f"{'' if not errors else f'; page errors: {len(errors)}'}")
    return 0 if ok else 1


# --- --fleet: the overview, one DCU opened from it, every DCU ------------------------------------

def heap_slope(samples: list[dict]) -> Figure:
    """The heap's least-squares slope over the samples, MiB per minute."""
    if len(samples) < 2:
        return NA("fewer than two heap samples")
    t = [(s["t"] - samples[0]["t"]) / 60000 for s in samples]
    h = [s["heap"] / 2**20 for s in samples]
    tm, hm = sum(t) / len(t), sum(h) / len(h)
    den = sum((x - tm) ** 2 for x in t)
    return ratio(sum((x - tm) * (y - hm) for x, y in zip(t, h)), den, "the samples were taken at one instant")


def state_summary(samples: list[dict], minutes: float) -> dict:
    """A state's figures: summarise()'s, the heap's slope and growth over the state's length, the
    WebSocket's kB/s, the DCUs the page held and the rows it listed."""
    out = summarise(samples, [])
    del out["page_errors"]
    slope = heap_slope(samples)
    measured = samples[1:]
    none = "no sample period was measured"
    out.update({
        "heap_slope_mib_per_min": slope, "heap_growth_mib": slope * minutes,
        "ws_kb_per_s": mean([s["ws_kbps"] for s in measured], none),
        "chromium_cores": mean([s["chromium_cores"] for s in measured], none),
        "load_cores": mean([s["load_cores"] for s in measured], none),
        "machine_busy_pct": mean([s["machine_busy_pct"] for s in measured], none),
        "dcus_held": samples[-1]["stores"], "overview_rows": samples[-1]["rows"],
        "heap_series_mib": [[round((s["t"] - samples[0]["t"]) / 1000), round(s["heap"] / 2**20, 1)] for s in samples],
    })
    return out


def fleet_state(browser, url: str, name: str, minutes: float, period: float, warmup: float, errors: list[str],
                page=None, traffic=None, before=None, cpu: CpuMeter | None = None) -> tuple[dict, object, Traffic]:
    """One state of the page measured for ``minutes``: on ``page`` as it is (after ``before(page)``),
    or a fresh page on ``url``; returns its figures, the page and its traffic counter."""
    if page is None:
        page, traffic = open_page(browser, url, errors)
    if before is not None:
        before(page)
    page.wait_for_timeout(warmup * 1000)
    samples = [page.evaluate(SAMPLE)]
    samples[0]["ws_bytes"] = traffic.bytes
    samples[0]["cpu"] = cpu.snapshot() if cpu is not None else {}
    print(f"-- {name}: {url.split('/', 3)[-1] or '/'} · {samples[0]['rows']} rows, {samples[0]['stores']} DCUs held"
          f" · warm-up {warmup:g} s", flush=True)
    measure(page, max(1, round(minutes * 60 / period)), period, samples, traffic, name, cpu)
    return state_summary(samples, minutes), page, traffic


def open_worst(page) -> None:
    """A click on the overview's first row (worst first) of a DCU that is up (a DCU down has nothing
    to draw); then until the page holds frames of it."""
    page.click(".tab[data-tab=stage]")
    rows = page.evaluate("() => window.dcuscope.debug().overview.rows")
    row = next((r for r in rows if not r["down"]), rows[0])
    page.click(f'#overview tbody tr[data-node="{row["node"]}"]')
    page.mouse.move(5, 5)
    page.wait_for_function("(n) => (window.dcuscope.debug().stores[n]?.received ?? 0) > 0", arg=row["node"],
                           timeout=120_000)
    print(f"opened {row['node']} from the overview (row {rows.index(row) + 1} of {len(rows)},"
          f" alerts: {'; '.join(row['alerts']) or 'none'})", flush=True)


def fleet(playwright, url: str, args: argparse.Namespace, errors: list[str]) -> dict[str, dict]:
    """The three states of --fleet (the docstring), each printed as it runs; their figures by name."""
    browser = launch_chromium(playwright, ["--enable-precise-memory-info", "--js-flags=--expose-gc"])
    print(f"load: {args.nodes} nodes x {args.sources} sources x {args.fps:g} fps = "
          f"{args.nodes * args.sources * args.fps:g} frames/s", flush=True)
    print(f"{HEADER} {'state':>8} {'kB/s ws':>8} {'chromium':>8} {'load':>7} {'busy%':>6}", flush=True)
    states = {}
    cpu = CpuMeter()
    home = url + ("/" if args.nodes > AUTO_OPEN_MAX else "/?open=")
    page, traffic = open_page(browser, home, errors)
    page.wait_for_function(f"() => window.dcuscope.debug().overview.total >= {args.nodes}", timeout=120_000)
    states["overview"], page, traffic = fleet_state(browser, home, "overview", args.minutes, args.heap_period,
                                                    args.warmup, errors, page, traffic, cpu=cpu)
    states["one"], page, traffic = fleet_state(browser, home, "one", args.open_minutes, args.period, 10.0, errors,
                                               page, traffic, before=open_worst, cpu=cpu)
    page.close()
    if not args.no_all:
        states["all"], page, _ = fleet_state(browser, url + "/?open=*", "all", args.open_minutes, args.period,
                                             args.warmup, errors, cpu=cpu)
        page.close()
    browser.close()
    return states


ROWS = [("lowest rAF/s in a period", "min_fps", ".1f"), ("mean rAF/s", "mean_fps", ".1f"),
        ("draw ms per frame (worst period mean)", "max_draw_ms_mean", ".2f"),
        ("JS heap start MiB", "heap_start_mib", ".1f"), ("JS heap end MiB", "heap_end_mib", ".1f"),
        ("JS heap highest MiB", "heap_max_mib", ".1f"), ("heap slope MiB/min", "heap_slope_mib_per_min", "+.2f"),
        ("DOM nodes (end)", "dom_end", "d"), ("frames/s received", "frames_per_s_in", ".0f"),
        ("kB/s pushed over the WebSocket", "ws_kb_per_s", ".1f"),
        ("Chromium CPU, cores", "chromium_cores", ".2f"), ("relay + nodes CPU, cores", "load_cores", ".2f"),
        ("machine busy %", "machine_busy_pct", ".0f"), ("DCUs held (stores)", "dcus_held", "d"),
        ("overview rows", "overview_rows", "d")]


def fleet_verdict(states: dict[str, dict], args: argparse.Namespace) -> tuple[bool, str]:
    ov, one = states["overview"], states["one"]
    checks = [
        (not missing(ov["min_fps"]) and ov["min_fps"] >= MIN_FPS, f"overview rAF >= {MIN_FPS:g}/s: {fmt(ov['min_fps'], '.1f')}"),
        (ov["heap_max_mib"] <= FLEET_HEAP_MAX_MB, f"heap <= {FLEET_HEAP_MAX_MB:g} MiB: {ov['heap_max_mib']:.1f}"),
        (not missing(ov["heap_growth_mib"]) and ov["heap_growth_mib"] <= HEAP_SLACK_MB,
         f"flat heap (slope x {args.minutes:g} min <= {HEAP_SLACK_MB:g} MiB): {fmt(ov['heap_growth_mib'], '+.1f')} MiB"),
        (not missing(one["min_fps"]) and one["min_fps"] >= MIN_FPS,
         f"one DCU opened rAF >= {MIN_FPS:g}/s: {fmt(one['min_fps'], '.1f')}"),
    ]
    ok = all(c for c, _ in checks)
    return ok, "; ".join(text for _, text in checks)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=5.0, help="measured time (after warm-up)")
    parser.add_argument("--nodes", type=int, default=2)
    parser.add_argument("--sources", type=int, help="per node (default 6; --follow-cpu: 3)")
    parser.add_argument("--fps", type=float, help="frames per second per source (default 60; --follow-cpu: 30)")
    parser.add_argument("--warmup", type=float, help="seconds before the first sample (default 20; --follow-cpu: 5)")
    parser.add_argument("--period", type=float, help="seconds per sample (default 10; --follow-cpu: 20, a mode)")
    parser.add_argument("--json", type=Path, help="write the samples and summary here")
    parser.add_argument("--quick", action="store_true",
                        help="a smoke test: 1 node x 2 sources x 30 fps, 1 s warm-up, two 1 s periods")
    parser.add_argument("--fleet", action="store_true",
                        help="the overview (for --minutes), one DCU opened from it and every DCU (for --open-minutes)")
    parser.add_argument("--open-minutes", type=float, default=1.0, help="--fleet: measured time of the one and all states")
    parser.add_argument("--heap-period", type=float, default=30.0, help="--fleet: seconds per sample of the overview")
    parser.add_argument("--no-all", action="store_true", help="--fleet: leave out the state with every DCU opened")
    parser.add_argument("--follow-cpu", action="store_true",
                        help="Chromium's CPU following live, redrawn every animation frame and as the page does")
    args = parser.parse_args(argv)
    defaults = {"sources": 3, "fps": 30.0, "warmup": 5.0, "period": 20.0} if args.follow_cpu else \
        {"sources": 6, "fps": 60.0, "warmup": 20.0, "period": 10.0}
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.follow_cpu:
        args.minutes = (len(FOLLOW_MODES) * (args.period + 1)) / 60
    if args.quick:
        args.nodes, args.sources, args.fps, args.warmup, args.period = 1, 2, 30.0, 1.0, 1.0
        args.minutes = 2 * args.period / 60
    if args.nodes < 1 or args.sources < 1 or args.fps <= 0 or args.period <= 0 or args.minutes <= 0:
        parser.error("--nodes, --sources, --fps, --period and --minutes must be positive")
    if args.fleet and (args.open_minutes <= 0 or args.heap_period <= 0):
        parser.error("--open-minutes and --heap-period must be positive")

    try:
        from playwright.sync_api import Error as PlaywrightError
        from playwright.sync_api import sync_playwright
    except ImportError as exc:
        raise CannotRun(f"Playwright is not installed ({exc})") from exc
    if not Path(CHROMIUM).exists():
        raise CannotRun(f"{CHROMIUM} not found: install Debian's chromium package")

    names = [f"DCU-{k + 1}" for k in range(args.nodes)]
    seconds = args.warmup + args.minutes * 60 + 5
    if args.fleet:  # the overview's wait for its rows, then the one and all states
        seconds += 120 + 10 + args.open_minutes * 60 + (0 if args.no_all else args.warmup + 60 + args.open_minutes * 60)
    errors: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-ui-") as tmp_name:
        tmp = Path(tmp_name)
        relay = Relay(tmp / "relay.db")
        feeder = sim_nodes(relay.url, tmp, names, frames=int(args.fps * seconds), sources=args.sources, fps=args.fps,
                           paced=True)
        try:
            with sync_playwright() as playwright:
                if args.follow_cpu:
                    states = follow_cpu(playwright, relay.url, args, errors)
                elif args.fleet:
                    states = fleet(playwright, relay.url, args, errors)
                else:
                    samples = watch(playwright, relay.url, args, errors)
        except PlaywrightError as exc:
            raise CannotRun(f"Chromium failed: {one_line(exc.message)}") from exc
        finally:
            feeder.stop()
            relay.stop()

    if args.follow_cpu:
        return report_follow(states, errors)
    if args.fleet:
        return report_fleet(states, errors, args)
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


def report_fleet(states: dict[str, dict], errors: list[str], args: argparse.Namespace) -> int:
    ov = states["overview"]
    print(f"overview heap series (s, MiB): {ov['heap_series_mib']}")
    print(f"overview heap slope: {fmt(ov['heap_slope_mib_per_min'], '+.3f')} MiB/min "
          f"({fmt(ov['heap_growth_mib'], '+.1f')} MiB over {args.minutes:g} min)")
    names = list(states)
    titles = {"overview": f"overview ({args.minutes:g} min)", "one": f"one DCU opened ({args.open_minutes:g} min)",
              "all": f"all {args.nodes} opened ({args.open_minutes:g} min)"}
    width = max(len(r[0]) for r in ROWS)
    print(f"{'':{width}} " + " ".join(f"{titles[n]:>26}" for n in names))
    for label, key, spec in ROWS:
        print(f"{label:{width}} " + " ".join(f"{fmt(states[n][key], spec):>26}" for n in names))
    ok, said = fleet_verdict(states, args)
    ok = ok and not errors
    summary = {"states": states, "page_errors": errors}
    print(f"{'PASS' if ok else 'FAIL'}: {said}{'' if not errors else f'; page errors: {len(errors)}'}")
    if args.json:
        args.json.write_text(dumps(summary, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(run(main))
