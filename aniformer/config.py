"""Config sections: frozen dataclasses that go to and from the plain dicts of YAML, checkpoints and MLflow.

One path each way: `from_dict` builds a section from its dict (unknown keys and bad values as one
`UserError` line), `Section.to_dict` gives the dict back. A `Section` holds sequences as tuples
however it was built (YAML, JSON and callers give lists), so sections compare and hash by value.
"""

from __future__ import annotations

import dataclasses

from aniformer.errors import UserError


class Section:
    """Base of the config dataclasses (``@dataclass(frozen=True) class X(Section)``); a subclass's own
    ``__post_init__`` calls ``super().__post_init__()`` first."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, list):
                object.__setattr__(self, f.name, tuple(value))

    def to_dict(self) -> dict:
        """The section as plain values (tuples as lists), as YAML would give it back."""
        return {f.name: _plain(getattr(self, f.name)) for f in dataclasses.fields(self)}


def _plain(value):
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def from_dict(cls: type, values: dict | None, section: str):
    """Build dataclass `cls` from a config section, naming unknown keys and bad values in one line."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise UserError(f"unknown key(s) in [{section}]: {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    try:
        return cls(**values)
    except (TypeError, ValueError) as e:
        raise UserError(f"[{section}] {e}") from None
