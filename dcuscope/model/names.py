"""How several traces of one node name are told apart: NODE, NODE_2, NODE_3... (different runs)."""

from __future__ import annotations


def unique_name(name: str, taken) -> str:
    """``name``, or ``name_2``, ``name_3``... the first not in ``taken``."""
    if name not in taken:
        return name
    k = 2
    while f"{name}_{k}" in taken:
        k += 1
    return f"{name}_{k}"


def unique_names(names) -> list[str]:
    """Each of ``names`` as :func:`unique_name` gives it after the ones before it."""
    out: list[str] = []
    for name in names:
        out.append(unique_name(name, out))
    return out
