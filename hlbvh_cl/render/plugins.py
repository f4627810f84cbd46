"""What every plugin spec of a scene's look shares (materials.py,
emitters.py): a dict with a "type" among the written ones, and only that
type's parameters, each error naming the entry."""
from __future__ import annotations

from collections.abc import Mapping


def plugin_type(name: str, spec, written: dict, example: dict, what: str) -> str:
    """The checked "type" of ``spec`` (one of ``written``, which maps each
    type to the parameters it takes); ``what`` names the kind in errors."""
    if not isinstance(spec, Mapping):
        raise TypeError(f"{name} must be a dict such as {example}, got {type(spec).__name__}")
    kind = spec.get("type")
    if not isinstance(kind, str) or kind not in written:  # (a list is no key of written)
        raise ValueError(f"{name}: type {kind!r} is not one of {tuple(written)} (the path "
                         f"integrator's {what} so far)")
    unknown = sorted(set(spec) - {"type", *written[kind]})
    if unknown:
        raise ValueError(f"{name}: {kind} takes {written[kind]}, not {unknown}")
    return kind
