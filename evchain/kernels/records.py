"""Parameter records of the kernels: ``typing.NamedTuple`` classes of scalars.

A kernel takes its constants as one record (numba unboxes a named tuple once per call, and its
fields are then plain locals), built once by the filter with :func:`record`, which converts every
value to its field's type: the kernel then compiles once whatever the caller passed (an ``int``
where a ``float`` is declared, a numpy scalar), and a missing or unknown field is an error.
"""

from __future__ import annotations

import typing
from typing import Any, TypeVar

R = TypeVar("R")


def record(cls: type[R], **values: Any) -> R:
    """``cls(**values)`` with each value converted to its field's annotated type."""
    hints = typing.get_type_hints(cls)
    fields = cls._fields  # type: ignore[attr-defined]
    missing = [f for f in fields if f not in values]
    unknown = [k for k in values if k not in fields]
    if missing or unknown:
        raise TypeError(f"{cls.__name__}: missing fields {missing}, unknown fields {unknown}")
    return cls(**{f: hints[f](values[f]) for f in fields})
