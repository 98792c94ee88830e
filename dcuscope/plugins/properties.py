"""GObject properties of dcuscope's elements, kept as plain attributes.

Property ``line-width`` lives in ``self.line_width``. An element lists its properties once,
``__gproperties__ = PROPERTIES = {...}``: PyGObject removes ``__gproperties__`` from the class
when it registers it, ``PROPERTIES`` stays for this mixin.
"""

from __future__ import annotations


def attribute(name: str) -> str:
    return name.replace("-", "_")


class AttributeProperties:
    """Mixin (before the GStreamer base class) giving ``do_get_property``/``do_set_property``."""

    PROPERTIES: dict = {}
    CHOICES: dict[str, tuple] = {}
    """Property -> every value it takes, where its GObject type cannot say so (a text property that
    is really an enum): the element refuses others when it starts, and a YAML configuration is
    checked against the same tuple before anything runs (``pipeline/elements.py``)."""

    def init_properties(self) -> None:
        """Every property at its default (the spec's second-to-last item, for every type)."""
        for name, spec in self.PROPERTIES.items():
            setattr(self, attribute(name), spec[-2])

    def do_get_property(self, prop):
        if prop.name not in self.PROPERTIES:
            raise AttributeError(f"unknown property {prop.name}")
        return getattr(self, attribute(prop.name))

    def do_set_property(self, prop, value):
        # Exceptions here are only printed by PyGObject: bad values are refused in do_start.
        if prop.name not in self.PROPERTIES:
            raise AttributeError(f"unknown property {prop.name}")
        setattr(self, attribute(prop.name), value)
        self.property_changed(prop.name)

    def property_changed(self, name: str) -> None:
        """Hook for elements that must react to a new value (renegotiate, ...)."""
