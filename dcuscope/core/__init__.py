"""The foundation every other package builds on, importing nothing of ours: GStreamer's GI
import (``gst``), the exception family's base (``errors``), clock ids (``clocks``), start-up
signals (``signals``), a console that survives a closed terminal (``console``), port checks
(``ports``)."""
