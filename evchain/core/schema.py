"""Parameter tables from a filter's ``Params`` schema (for ``evchain filters NAME`` and docs)."""

from __future__ import annotations

from typing import Any

from pydantic_core import PydanticUndefined

from evchain.core.filter import Filter

_BOUND_NAMES = {"gt": ">", "ge": ">=", "lt": "<", "le": "<=", "multiple_of": "multiple of",
                "min_length": "min length", "max_length": "max length"}


def _type_name(annotation: Any) -> str:
    text = getattr(annotation, "__name__", None) if isinstance(annotation, type) else None
    text = text or str(annotation)
    return (text.replace("typing.", "").replace("pathlib.", "").replace("<class '", "")
            .replace("'>", ""))


def field_rows(cls: type[Filter]) -> list[dict[str, str]]:
    """One row per parameter: name, type, default, bounds, description."""
    rows = []
    for name, info in cls.Params.model_fields.items():
        bounds = []
        for meta in info.metadata:
            for attr, label in _BOUND_NAMES.items():
                value = getattr(meta, attr, None)
                if value is not None:
                    bounds.append(f"{label} {value}")
        if info.default is PydanticUndefined and info.default_factory is None:
            default = "(required)"
        elif info.default_factory is not None:
            default = repr(info.default_factory())
        else:
            default = repr(info.default)
        rows.append({"name": name, "type": _type_name(info.annotation), "default": default,
                     "bounds": ", ".join(bounds), "description": info.description or ""})
    return rows


def describe_filter(cls: type[Filter], distribution: str) -> str:
    """Human-readable reference of one filter: doc, wiring and parameter table."""
    consumes = cls.consumes.__name__ if cls.consumes else "(source)"
    produces = cls.produces.__name__ if cls.produces else "(same as input)"
    lines = [f"{cls.name}  [{distribution}]  {consumes} -> {produces}", ""]
    lines += [ln.rstrip() for ln in (cls.__doc__ or "").strip().splitlines()]
    lines += ["", "parameters:"]
    rows = field_rows(cls)
    if not rows:
        lines.append("  (none)")
    for r in rows:
        bounds = f"  [{r['bounds']}]" if r["bounds"] else ""
        lines.append(f"  {r['name']}: {r['type']} = {r['default']}{bounds}")
        if r["description"]:
            lines.append(f"      {r['description']}")
    return "\n".join(lines)
