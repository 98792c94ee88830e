"""One stream count, in a process of its own: ``python -m dcuscope.capacity.count SPEC.json``.

SPEC says the config, the stream count, how its sources are given (:func:`.plan.for_streams`), the
trace file and the run's length, counted from the first frame at the sink (a start slowed by a loaded
machine does not eat the frames measured). The run is ``dcuscope run``'s: the same build, probes and runner.
The last line on stdout is one JSON object: the process's CPU time sampled through the run, and
what the runner says went wrong (a source lost, an abort).
"""

from __future__ import annotations

import json
import sys
import threading
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
        runner = Runner(built, duration=spec["duration"], progress=None, duration_after_first_frame=True)
        probing = start_probes(built, config, progress=None)
        samples = CpuSamples()
        try:
            result = runner.run()
        finally:
            samples.stop()
            probing.stop()
    finally:
        built.close()
    lost = {str(i): reason for i, reason in result.dead_sources.items()}
    return {"cpu": samples.taken, "lost": lost, "aborted": result.aborted}


class CpuSamples:
    """(wall clock s, this process's CPU s) twice a second while the pipeline runs: the parent takes
    the CPU rate over the frames it measures (after the warm-up: the model's load and the first
    batches cost CPU that a running pipeline does not)."""

    PERIOD_S = 0.5

    def __init__(self):
        self.taken: list[tuple[float, float]] = []
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cpu-samples", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self.taken.append((time.time(), time.process_time()))
            if self._done.wait(self.PERIOD_S):
                self.taken.append((time.time(), time.process_time()))
                return

    def stop(self) -> None:
        self._done.set()
        self._thread.join()


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
