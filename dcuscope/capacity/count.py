"""One stream count, in a process of its own: ``python -m dcuscope.capacity.count SPEC.json``.

SPEC says the config, the stream count, how its sources are given (:func:`.plan.for_streams`), the
trace file and the run's length. The run is ``dcuscope run``'s: the same build, probes and runner.
The last line on stdout is one JSON object: the CPU the run used (after start-up), its wall time,
and what the runner says went wrong (a source lost, an abort).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

from dcuscope.core.errors import ConfigError, DcuscopeError, UsageError


def run_count(spec: dict) -> dict:
    from dcuscope.capacity.plan import for_streams
    from dcuscope.pipeline.build import build_pipeline
    from dcuscope.pipeline.config import load_config
    from dcuscope.pipeline.run import Runner
    from dcuscope.probes.instrument import start_probes

    config = load_config(spec["config"])
    config = for_streams(config, spec["streams"], spec["keep_batch"], spec.get("rtsp_uris"),
                         spec.get("mux_timeout_us"))
    config = replace(config, probes=replace(config.probes, enabled=True, trace=Path(spec["trace"])))
    built = build_pipeline(config)
    try:
        runner = Runner(built, duration=spec["duration"], progress=None)
        probing = start_probes(built, config, progress=None)
        cpu0, wall0 = time.process_time(), time.monotonic()
        try:
            result = runner.run()
        finally:
            cpu_s, wall_s = time.process_time() - cpu0, time.monotonic() - wall0
            probing.stop()
    finally:
        built.close()
    lost = {str(i): reason for i, reason in result.dead_sources.items()}
    return {"cpu_s": cpu_s, "wall_s": wall_s, "lost": lost, "aborted": result.aborted}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    spec = json.loads(Path(argv[0]).read_text())
    try:
        out = run_count(spec)
    except DcuscopeError as exc:  # a bad config or property: the parent says it as bad input
        out = {"error": str(exc), "bad_input": isinstance(exc, (ConfigError, UsageError))}
    print(json.dumps(out), flush=True)
    return 0 if "error" not in out and not out["aborted"] else 1


if __name__ == "__main__":
    sys.exit(main())
