"""Running a built pipeline: main loop, bus, progress, limits, Ctrl-C or SIGTERM -> EOS -> clean stop.

A stop (``--num-frames``, ``--duration``, the first Ctrl-C, SIGTERM) ends the run with
end-of-stream, so that the sink finishes (an MP4 gets its index). Files drain: every frame read
goes through. Live sources do not wait for a pipeline that lags, so a live run that drained
would stop only when its backlog ran out, however long it is: it stops at once instead
(:mod:`dcuscope.pipeline.livestop`), the frames still queued counted as dropped. Only Ctrl-C while
stopping aborts; SIGTERM is always the clean stop (what service managers and ``timeout`` send).
"""

from __future__ import annotations

import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, TextIO

from dcuscope.core import signals
from dcuscope.core.clocks import NEVER
from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import GLib, Gst
from dcuscope.pipeline.build import BuiltPipeline
from dcuscope.pipeline.livestop import LiveStop
from dcuscope.pipeline.sourcefaults import describe_fault
from dcuscope.pipeline.stalls import Stall, StallWatch
from dcuscope.plugins.frames import read_frames

EOS_GRACE_S = 15.0
"""How long a stop waits for end-of-stream at the sink with no frame reaching the sink meanwhile: a
pipeline still draining its backlog (a loaded machine, a slow detector) is waited for, a stuck one
is not. Longer where frames came further apart: :data:`GAPS_GRACE` times the longest gap between two
frames at the sink, up to :data:`EOS_GRACE_MAX_S` (a detector at a frame in 20 s, as an emulated
aarch64 DCU runs it)."""
GAPS_GRACE = 3.0
EOS_GRACE_MAX_S = 120.0


@dataclass
class RunResult:
    frames: int = 0
    """Buffers that reached the sink (with several sources, each a collage or batch of camera frames)."""
    camera_frames: int = 0
    """The camera frames those buffers carry (their identity meta), 0 where frames carry none."""
    past_limit: int = 0
    """Buffers that reached the sink after ``--num-frames`` was reached (they had passed every stage:
    a trace counts their frames complete), dropped there."""
    past_limit_camera_frames: int = 0
    seconds: float = 0.0
    interrupted: bool = False
    """Stopped by Ctrl-C or SIGTERM."""
    aborted: str | None = None
    """Why the run ended before end-of-stream reached the sink (a second Ctrl-C, EOS too slow):
    the sink did not finish (an MP4 without its index), or None."""
    discarded: int = 0
    """Live runs: frames still queued when the stop came, dropped rather than drained (each one
    posted as dropped, reason ``stopped``)."""
    dead_sources: dict[int, str] = field(default_factory=dict)
    stalls: dict[int, list[Stall]] = field(default_factory=dict)
    """Live sources that went quiet for longer than their stall-timeout, and for how long."""

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0


class Runner:
    """Runs ``built`` until EOS, a frame or time limit, Ctrl-C, or an error.

    A source that fails (dead camera, stream gone) is reported and dropped; the others go on.
    Any other error stops the run with PipelineError.
    """

    def __init__(self, built: BuiltPipeline, num_frames: int | None = None, duration: float | None = None,
                 progress: TextIO | None = sys.stderr, progress_every: float = 1.0, traced: bool = False,
                 duration_after_first_frame: bool = False):
        self.built = built
        self.traced = traced
        """Whether probes trace the run (the final line then says how a trace counts frames)."""
        self.num_frames = num_frames
        self.duration = duration
        self.duration_after_first_frame = duration_after_first_frame
        """``duration`` counts from the first frame at the sink, not from PLAYING (a capacity count:
        a start slowed by a loaded machine must not eat the frames it measures)."""
        self.progress = progress
        self.progress_every = progress_every
        self.result = RunResult()
        self.on_progress: list[Callable[[RunResult], None]] = []
        self._loop = GLib.MainLoop()
        self._error: str | None = None
        self._retired: set = set()  # every element of the sources dropped so far
        self._stop_asked_at: float | None = None
        self._last_frame_at = NEVER
        """When the last frame reached the sink (counted or, past --num-frames, dropped there)."""
        self._first_frame_at = NEVER
        self._longest_gap = 0.0
        """The longest time between two frames reaching the sink."""
        self._stopped_by: str | None = None  # what asked for the stop: Ctrl-C, SIGTERM, a limit
        self._live_stop: LiveStop | None = None
        self._started: float | None = None  # time.monotonic() once PLAYING
        self._last_report = (NEVER, 0)
        self._stalls = StallWatch(self._say, self.result.stalls)

    # -- public ----------------------------------------------------------------------------
    def run(self) -> RunResult:
        pipeline = self.built.pipeline
        sink_pad = self.built.sink.get_static_pad("sink") or self.built.sink.sinkpads[0]
        sink_pad.add_probe(Gst.PadProbeType.BUFFER, self._count_frame)
        bus = pipeline.get_bus()
        bus.add_signal_watch()
        handler = bus.connect("message", self._on_message)
        sigint = GLib.unix_signal_add(GLib.PRIORITY_HIGH, signal.SIGINT, self._on_sigint)
        sigterm = GLib.unix_signal_add(GLib.PRIORITY_HIGH, signal.SIGTERM, self._on_sigterm)
        ticker = GLib.timeout_add(200, self._tick)
        try:
            if signals.held() is not None:
                self.result.interrupted = True
                self._say("stopped before the pipeline started")
            elif pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
                self._error = self._error or self._drain_error(bus) or "the pipeline could not start"
            else:
                self._started = time.monotonic()
                self._stalls.start(self.built.sources, self._started)
                self._loop.run()
        finally:
            GLib.source_remove(ticker)
            GLib.source_remove(sigint)
            GLib.source_remove(sigterm)
            signals.finishing()  # GLib left the default (fatal) actions; a stop is under way or done
            self.result.seconds = time.monotonic() - self._started if self._started is not None else 0.0
            self._stalls.finish(time.monotonic())
            pipeline.set_state(Gst.State.NULL)
            if self._live_stop is not None:
                self.result.discarded = self._live_stop.dropped
            bus.disconnect(handler)
            bus.remove_signal_watch()
            self._report(final=True)
        if self._error:
            raise PipelineError(self._error)
        return self.result

    @property
    def live(self) -> bool:
        """Some source sends frames in real time (camera, stream, live file or test)."""
        return any(s.config.is_live for s in self.built.sources)

    def stop(self) -> None:
        """Ask for a clean stop: end-of-stream from every source, then wait for it to reach the sink.
        Files drain; live sources end now, and the frames still queued are dropped (:mod:`dcuscope.pipeline.livestop`)."""
        if self._stop_asked_at is not None:
            return
        self._stop_asked_at = time.monotonic()
        if self.live:
            clock_id = self.built.sources[0].stamp.get_property("clock-id")
            self._live_stop = LiveStop(self.built.stages, self._live_sources(), clock_id)
            self._live_stop.start()
            return
        for source in self.built.sources:
            source.stop_looping()
        self.built.pipeline.send_event(Gst.Event.new_eos())

    # -- callbacks -------------------------------------------------------------------------
    def _count_frame(self, _pad, info):
        now = time.monotonic()
        if self._last_frame_at != NEVER:
            self._longest_gap = max(self._longest_gap, now - self._last_frame_at)
        else:
            self._first_frame_at = now
        self._last_frame_at = now
        carried = len(read_frames(info.get_buffer()))
        if self.num_frames is not None and self.result.frames >= self.num_frames:
            self.result.past_limit += 1
            self.result.past_limit_camera_frames += carried
            return Gst.PadProbeReturn.DROP  # frames still in flight after the limit
        self.result.frames += 1
        self.result.camera_frames += carried
        if self.num_frames is not None and self.result.frames == self.num_frames:
            GLib.idle_add(self._stop_once)
        return Gst.PadProbeReturn.OK

    def _stop_once(self):
        self.stop()
        return False

    def _on_sigint(self):
        if self._stop_asked_at is None:
            self._stop_for("Ctrl-C")
        else:  # a stop under way takes too long for the user: leave the sink unfinished
            self.result.interrupted = True
            self.result.aborted = ("aborted by a second Ctrl-C" if self._stopped_by == "Ctrl-C"
                                   else "aborted by Ctrl-C while stopping")
            self._loop.quit()
            self._say("\naborting")
        return True

    def _on_sigterm(self):
        """Always the clean stop, never an abort: a service manager or ``timeout`` that sends it
        again, or after a ``--duration`` stop began, means "stop", which is under way."""
        if self._stop_asked_at is None:
            self._stop_for("SIGTERM")
        else:
            self._say("\nSIGTERM: already stopping (Ctrl-C to abort)")
        return True

    def _stop_for(self, why: str) -> None:
        if self._started is not None:  # frames that came since the last tick (a stream's catch-up burst) are said
            self._stalls.update(self._live_sources(), time.monotonic())
        self._stopped_by = why
        if why in ("Ctrl-C", "SIGTERM"):
            self.result.interrupted = True
        self.stop()
        dropping = "; frames still queued are dropped" if self.live else ""
        again = "Ctrl-C again" if why == "Ctrl-C" else "Ctrl-C"
        on = "" if why == "Ctrl-C" else f" ({why})"
        self._say(f"\nstopping{on}: sending end-of-stream{dropping} ({again} to abort)")

    def _tick(self):
        now = time.monotonic()
        started = self._started is not None
        since = self._first_frame_at if self.duration_after_first_frame else self._started
        if started and self.duration is not None and self._stop_asked_at is None and since != NEVER \
                and now - since >= self.duration:
            self._stop_for(f"--duration {self.duration:g} s")
        grace = min(max(EOS_GRACE_S, GAPS_GRACE * self._longest_gap), EOS_GRACE_MAX_S)
        if self._stop_asked_at is not None and now - max(self._stop_asked_at, self._last_frame_at) > grace:
            self._say(f"\nend-of-stream did not reach the sink, nor any frame, within {grace:.0f} s: "
                      "stopping anyway")
            self.result.aborted = "end-of-stream did not reach the sink"
            self._loop.quit()
        if started and self._stop_asked_at is None:
            self._stalls.update(self._live_sources(), now)
        if now - self._last_report[0] >= self.progress_every:
            self._report()
        return True

    def _on_message(self, _bus, message: Gst.Message):
        if message.type == Gst.MessageType.EOS:
            if self._started is not None and self._stop_asked_at is None:
                self._stalls.update(self._live_sources(), time.monotonic())  # the last live source's end, said
            self._loop.quit()
        elif message.type == Gst.MessageType.ERROR:
            self._on_error(message)
        elif message.type == Gst.MessageType.WARNING:
            err, debug = message.parse_warning()
            source = self._source_of(message.src)
            if source is not None:
                where = f"source {source.index} ({source.config.description})"
                text = describe_fault(err, debug, source.config.location)
            else:
                where, text = message.src.get_name() if message.src else "pipeline", err.message
            self._say(f"\nwarning: {where}: {text}")

    def _on_error(self, message: Gst.Message) -> None:
        err, debug = message.parse_error()
        if message.src in self._retired:
            return  # the aftershocks of a source already retired, whatever bin still holds the element
        source = self._source_of(message.src)
        if source is None:
            where = message.src.get_path_string() if message.src else "pipeline"
            self._error = f"{where}: {err.message}" + (f" ({debug.splitlines()[0]})" if debug else "")
            self._loop.quit()
            return
        reason = describe_fault(err, debug, source.config.location)
        if self._stop_asked_at is None and len(self._live_sources()) > 1:
            self._drop_source(source, reason)
        else:
            self._error = f"source {source.index} ({source.config.description}): {reason}"
            self._loop.quit()

    # -- helpers ---------------------------------------------------------------------------
    def _source_of(self, obj) -> object | None:
        while obj is not None:
            if obj in self.built.sources:
                return obj
            obj = obj.get_parent()
        return None

    def _live_sources(self):
        return [s for s in self.built.sources if s.index not in self.result.dead_sources]

    def _drop_source(self, source, reason: str) -> None:
        """A camera or stream died: report it, end its stream into the mux, keep the rest running."""
        self.result.dead_sources[source.index] = reason
        # Snapshot the whole source bin now: on the way to NULL, uridecodebin unparents its rtspsrc
        # before that element posts its last "could not write" error, so the parent chain is gone.
        self._retired.add(source)
        self._retired.update(source.iterate_recurse())
        self._say(f"\nsource {source.index} ({source.config.description}) failed: {reason}; the other sources go on")
        source.stop_looping()
        pad = source.get_static_pad("src").get_peer()

        def retire():
            source.set_locked_state(True)
            source.set_state(Gst.State.NULL)
            if pad is not None:
                pad.send_event(Gst.Event.new_eos())
            return False

        GLib.idle_add(retire)

    def _drain_error(self, bus: Gst.Bus) -> str | None:
        msg = bus.pop_filtered(Gst.MessageType.ERROR)
        if msg is None:
            return None
        err, _debug = msg.parse_error()
        return f"{msg.src.get_path_string()}: {err.message}"

    def _report(self, final: bool = False) -> None:
        now = time.monotonic()
        last_t, last_frames = self._last_report
        self._last_report = (now, self.result.frames)
        for callback in self.on_progress:
            callback(self.result)
        if self.progress is None or self._started is None:
            return
        elapsed = now - self._started
        rate = (self.result.frames - last_frames) / (now - last_t) if last_t != NEVER and now > last_t else 0.0
        if final:
            line = f"{self.result.frames} frames in {elapsed:.1f} s ({self.result.frames / elapsed if elapsed else 0:.1f} fps)"
            line += self._what_was_counted()
        else:
            target = f"/{self.num_frames}" if self.num_frames else ""
            line = f"{elapsed:7.1f} s  frames {self.result.frames}{target}  {rate:5.1f} fps"
        tty = self.progress.isatty()
        self.progress.write(("\r" + line + ("\n" if final else "")) if tty else line + "\n")
        self.progress.flush()

    def _what_was_counted(self) -> str:
        """What the count is, where a trace of the run counts otherwise: camera frames (a buffer at
        the sink may carry several), and frames past ``--num-frames`` (processed, then not written)."""
        r = self.result
        text = ""
        if r.camera_frames and r.camera_frames != r.frames:
            text += f", {r.camera_frames} camera frames in them"
        if r.past_limit:
            them = "it" if r.past_limit == 1 else "them"
            camera = f" ({r.past_limit_camera_frames} camera frames)" if r.past_limit_camera_frames != r.past_limit else ""
            text += (f"; {r.past_limit} more{camera} had passed every stage when the limit was reached and "
                     f"{'was' if r.past_limit == 1 else 'were'} not written"
                     + (f" (a trace counts {them} complete)" if self.traced else ""))
        return text

    def _say(self, text: str) -> None:
        if self.progress is not None:
            self.progress.write(text + "\n")
            self.progress.flush()
