"""Source bins: a file, stream, camera, test pattern or another pipeline -> RGB frames stamped with
their identity.

    uridecodebin | v4l2src ! decodebin | videotestsrc
      | udpsrc ! rtpjitterbuffer ! rtpH264depay ! decodebin      (rtp: another pipeline's RTP)
      | shmsrc ! capsfilter(the sender's format, size, rate)    (shm: another pipeline's frames)
        ! videoconvert ! videoscale ! [videorate] ! capsfilter(RGB[, size][, rate])
        ! [clocksync: a live file, paced like a camera] ! framestamp

Frames from another pipeline are new frames here; the dcuscope tracer (--probes) records where
each came from, so that the relay joins it to the frame the other pipeline sent (docs/journeys.md).

A looping file seeks back to its start at EOS; the EOS and the flush stay inside the bin and
the bin's output running time goes on (pad offset), so the mux never sees the loop. Its
segments are open-ended and its length unknown downstream: it has no end. A file that cannot
loop says so on the bus (a warning naming the source) and ends there.
"""

from __future__ import annotations

import threading
from typing import Callable

from dcuscope.core.errors import PipelineError
from dcuscope.core.gst import GLib, Gst
from dcuscope.pipeline.config import SourceConfig


RTP_CAPS = {
    "H264": "application/x-rtp,media=video,encoding-name=H264,clock-rate=90000",
    "H265": "application/x-rtp,media=video,encoding-name=H265,clock-rate=90000",
    "JPEG": "application/x-rtp,media=video,encoding-name=JPEG,clock-rate=90000",
}


class SourceBin(Gst.Bin):
    """One camera/file of the pipeline, source id ``index``; its src pad gives stamped RGB frames."""

    def __init__(self, config: SourceConfig, index: int, clock_id: int):
        super().__init__(name=f"source{index}")
        self.config = config
        self.index = index
        self._stopping = False
        self._loop_offset = 0

        convert = _make("videoconvert", f"convert{index}")
        scale = _make("videoscale", f"scale{index}")
        caps = "video/x-raw,format=RGB"
        if config.width and config.height:
            caps += f",width={config.width},height={config.height}"
        chain = [convert, scale]
        if config.rate is not None and config.kind != "shm":  # shm: the rate the sender's caps say
            chain.append(_make("videorate", f"rate{index}"))
            caps += f",framerate={config.rate.numerator}/{config.rate.denominator}"
        capsfilter = _make("capsfilter", f"caps{index}")
        capsfilter.set_property("caps", Gst.Caps.from_string(caps))
        chain.append(capsfilter)
        if config.live and config.kind == "uri":
            chain.append(_make("clocksync", f"pace{index}"))  # a file played in real time, like a camera
        self.stamp = _make("framestamp", f"src{index}")
        self.stamp.set_property("source-id", index)
        self.stamp.set_property("clock-id", clock_id)
        chain.append(self.stamp)
        for element in chain:
            self.add(element)
        for a, b in zip(chain, chain[1:]):
            a.link(b)
        self._entry = convert.get_static_pad("sink")

        self.origin = self._make_origin()
        self.add(self.origin)
        if config.kind == "uri":
            self.origin.connect("pad-added", self._on_pad_added)
        elif config.kind in ("camera", "rtp"):
            before = [self.origin] + (self._rtp_receiver() if config.kind == "rtp" else [])
            decode = _make("decodebin", f"decode{index}")
            for element in before[1:] + [decode]:
                self.add(element)
            for a, b in zip(before, before[1:] + [decode]):
                a.link(b)
            decode.connect("pad-added", self._on_pad_added)
        elif config.kind == "shm":
            caps = _make("capsfilter", f"shmcaps{index}")
            caps.set_property("caps", Gst.Caps.from_string(
                f"video/x-raw,format={config.format},width={config.width},height={config.height},"
                f"framerate={config.rate.numerator}/{config.rate.denominator}"))
            self.add(caps)
            self.origin.link(caps)
            caps.link(convert)
        else:
            self.origin.link(convert)

        out = self.stamp.get_static_pad("src")
        self.add_pad(Gst.GhostPad.new("src", out))
        if config.loop:  # before the pacing, which must see the running time go on
            looped = capsfilter.get_static_pad("src")
            looped.add_probe(Gst.PadProbeType.EVENT_DOWNSTREAM | Gst.PadProbeType.EVENT_FLUSH, self._on_event)
            looped.add_probe(Gst.PadProbeType.QUERY_UPSTREAM, _endless)

    def _make_origin(self) -> Gst.Element:
        cfg = self.config
        if cfg.kind == "uri":
            element = _make("uridecodebin", f"decode{self.index}")
            element.set_property("uri", cfg.location)
            element.connect("source-setup", self._on_source_setup)
        elif cfg.kind == "camera":
            element = _make("v4l2src", f"camera{self.index}")
            element.set_property("device", cfg.location)
        elif cfg.kind == "rtp":
            element = _make("udpsrc", f"rtp{self.index}")
            element.set_property("port", int(cfg.location))
            element.set_property("caps", Gst.Caps.from_string(RTP_CAPS[cfg.encoding]))
        elif cfg.kind == "shm":
            element = _make("shmsrc", f"shm{self.index}")
            element.set_property("socket-path", cfg.location)
            element.set_property("is-live", True)
            # Timestamped as they come: the tracer finds each frame's bytes again by its PTS.
            element.set_property("do-timestamp", True)
        else:
            element = _make("videotestsrc", f"pattern{self.index}")
            Gst.util_set_object_arg(element, "pattern", cfg.location)
            element.set_property("is-live", cfg.live)
        return element

    def _rtp_receiver(self) -> list[Gst.Element]:
        """Jitter buffer and depayloader of an rtp: source, in order."""
        jitter = _make("rtpjitterbuffer", f"jitter{self.index}")
        if self.config.latency_ms is not None:
            jitter.set_property("latency", self.config.latency_ms)
        depay = _make(f"rtp{self.config.encoding.lower()}depay", f"depay{self.index}")
        return [jitter, depay]

    def _on_source_setup(self, _decodebin, source: Gst.Element) -> None:
        if self.config.latency_ms is not None and source.find_property("latency") is not None:
            source.set_property("latency", self.config.latency_ms)
        if source.find_property("add-reference-timestamp-meta") is not None:
            # rtspsrc: its jitter buffer then attaches each frame's capture time on the sender's
            # clock (timestamp/x-ntp, from RTCP sender reports, once the first has come), which
            # depayloader and decoder carry to the frame: plugins.frames.capture_ns reads it.
            source.set_property("add-reference-timestamp-meta", True)

    @property
    def frames(self) -> int:
        """Frames this source has delivered so far (read without a probe: the stamp counts them)."""
        return self.stamp.count

    @property
    def ended(self) -> bool:
        """Its end-of-stream has gone out to the mux."""
        return self.stamp.get_static_pad("src").get_sticky_event(Gst.EventType.EOS, 0) is not None

    def _on_pad_added(self, _element, pad: Gst.Pad) -> None:
        caps = pad.get_current_caps() or pad.query_caps(None)
        if caps.is_empty() or not caps[0].get_name().startswith("video/"):
            self._discard(pad)
            return
        if self._entry.is_linked():
            self._discard(pad)  # a second video stream in the same file: the first one wins
            return
        result = pad.link(self._entry)
        if result != Gst.PadLinkReturn.OK:
            self._post(Gst.Message.new_error, f"cannot link its decoded video: {result.value_nick}")

    def _discard(self, pad: Gst.Pad) -> None:
        sink = _make("fakesink", None)
        sink.set_property("sync", False)
        sink.set_property("async", False)
        self.add(sink)
        sink.sync_state_with_parent()
        pad.link(sink.get_static_pad("sink"))

    # -- looping ---------------------------------------------------------------------------
    def stop_looping(self) -> None:
        """Let the next EOS through (the run is ending)."""
        self._stopping = True

    def end_now(self) -> None:
        """End this source's stream at its frame stamp, now (a live run that stops): what comes
        from upstream is discarded before it is stamped (no identity, so never a frame of the
        run), and end-of-stream goes out right behind the last frame that was stamped."""
        self._stopping = True
        eos = Gst.Event.new_eos()
        ours = eos.get_seqnum()

        def discard(_pad: Gst.Pad, info: Gst.PadProbeInfo):
            if info.type & (Gst.PadProbeType.EVENT_DOWNSTREAM | Gst.PadProbeType.EVENT_FLUSH):
                event = info.get_event()  # a buffer's probe info has none: asking is a GStreamer-CRITICAL
                if event.type == Gst.EventType.EOS and event.get_seqnum() == ours:
                    return Gst.PadProbeReturn.OK
            return Gst.PadProbeReturn.DROP  # frames, and events that would reopen the stream (a loop's flush)

        entry = self.stamp.get_static_pad("sink")
        entry.add_probe(Gst.PadProbeType.BUFFER | Gst.PadProbeType.BUFFER_LIST | Gst.PadProbeType.EVENT_DOWNSTREAM
                        | Gst.PadProbeType.EVENT_FLUSH, discard)
        # Serialised on the stamp's streaming lock: it waits for a frame being stamped, or one
        # blocked on its way into a full mux, to go first. That can take a batch's time: not on
        # the main loop.
        threading.Thread(target=entry.send_event, args=(eos,), name=f"end-{self.index}", daemon=True).start()

    def _on_event(self, pad: Gst.Pad, info: Gst.PadProbeInfo):
        event = info.get_event()
        if self._stopping:
            return Gst.PadProbeReturn.OK
        if event.type in (Gst.EventType.FLUSH_START, Gst.EventType.FLUSH_STOP):
            return Gst.PadProbeReturn.DROP  # our own seek's flush: nothing downstream to flush
        if event.type == Gst.EventType.SEGMENT:
            return _open_ended(pad, event)
        if event.type == Gst.EventType.EOS:
            ok, duration = self.origin.query_duration(Gst.Format.TIME)
            if not ok or duration <= 0:
                self._post(Gst.Message.new_warning, "cannot loop: its length is unknown; it ends here")
                return Gst.PadProbeReturn.OK
            self._loop_offset += duration
            pad.set_offset(self._loop_offset)
            threading.Thread(target=self._rewind, name=f"loop-{self.index}", daemon=True).start()
            return Gst.PadProbeReturn.DROP
        return Gst.PadProbeReturn.OK

    def _rewind(self) -> None:
        seek = Gst.Event.new_seek(1.0, Gst.Format.TIME, Gst.SeekFlags.FLUSH | Gst.SeekFlags.KEY_UNIT,
                                  Gst.SeekType.SET, 0, Gst.SeekType.NONE, -1)
        if not self._entry.push_event(seek):  # upstream, from the first converter's sink pad
            self._post(Gst.Message.new_warning, "cannot loop: it cannot seek back to its start; it ends here")
            self._stopping = True
            self.stamp.get_static_pad("sink").send_event(Gst.Event.new_eos())

    def _post(self, new_message: Callable[[Gst.Object, GLib.Error, str], Gst.Message], text: str) -> None:
        """An error or warning from this source on the bus, where the runner reports it by the source's name."""
        error = GLib.Error.new_literal(Gst.StreamError.quark(), text, Gst.StreamError.FAILED)
        self.post_message(new_message(self, error, ""))


def _open_ended(pad: Gst.Pad, event: Gst.Event) -> Gst.PadProbeReturn:
    """A looping source never ends, so its segments must not either: the file's segment stops at
    its length, which an RTSP server announces as ``Range: npt=0-LENGTH`` and at which its clients
    (rtspsrc's jitter buffer) end the stream."""
    segment = event.parse_segment()
    if segment.stop == Gst.CLOCK_TIME_NONE:
        return Gst.PadProbeReturn.OK
    segment.stop = Gst.CLOCK_TIME_NONE
    segment.offset_running_time(Gst.Format.TIME, -pad.get_offset())  # the pad adds its offset again on the way out
    endless = Gst.Event.new_segment(segment)
    endless.set_seqnum(event.get_seqnum())
    pad.push_event(endless)  # comes back through this probe, open-ended this time
    return Gst.PadProbeReturn.DROP


def _endless(_pad: Gst.Pad, info: Gst.PadProbeInfo):
    """Nor has a looping source a length (an RTSP server asks for it with a duration or a segment
    query), nor can it be seeked from downstream (the seek would meet the loop's own flush
    handling): such queries stay unanswered."""
    if info.get_query().type in (Gst.QueryType.DURATION, Gst.QueryType.SEEKING, Gst.QueryType.SEGMENT):
        return Gst.PadProbeReturn.DROP
    return Gst.PadProbeReturn.OK


def _make(factory: str, name: str | None) -> Gst.Element:
    element = Gst.ElementFactory.make(factory, name)
    if element is None:
        raise PipelineError(f"GStreamer element {factory!r} is missing: is the setup complete? (make setup)")
    return element
