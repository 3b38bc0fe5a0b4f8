"""Pipelines: YAML (safe loading only), validated in two passes, with command-line overrides.

A pipeline file::

    name: quickstart        # optional, defaults to the file's stem
    seed: 7                 # optional, default 0
    description: ...        # optional
    chain:
      - use: aedat          # a registered filter name
        id: reader          # optional; needed to tell two stages of one filter apart
        path: tests/data/x.aedat   # every other key is a parameter of that filter

Pass 1 checks this shape; pass 2 checks each stage's keys against its filter's ``Params``, then
the wiring (each stage consumes what its predecessor produces and finds the series it needs added
by a stage before it) and that every stage has its own name (two stages of one filter need
``id:`` keys). Every error names ``file:line:column``, the key and what is allowed. Overrides
``STAGE.PARAM=VALUE`` address a stage by ``id`` or ``use`` name; the value is parsed as YAML
(``0.3``, ``true``, ``[1, 2]``).

Files: a stage's input files (its filter's ``input_paths``) are made absolute, relative to the
pipeline file's folder (``--set`` values: to the current folder), and must exist; its output
files (``output_paths``) must lie inside the run folder.
"""

from __future__ import annotations

import dataclasses
import difflib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from pydantic import ValidationError

from evchain.core.filter import Filter, FilterParams
from evchain.core.packets import Packet
from evchain.core.registry import Registry, unknown_filter_message
from evchain.core.series import SeriesDef
from evchain.errors import ConfigError, WiringError

TOP_KEYS = {"name": "a string", "seed": "an integer", "description": "a string",
            "chain": "a list of stages"}


@dataclass(frozen=True)
class Mark:
    """A place in a pipeline file (1-based line and column)."""

    file: str
    line: int | None = None
    column: int | None = None


@dataclass
class StageSpec:
    """One validated stage of a chain."""

    use: str
    id: str
    cls: type[Filter]
    params: FilterParams
    mark: Mark
    key_marks: dict[str, Mark] = field(default_factory=dict)


@dataclass
class PipelineSpec:
    """A validated pipeline: name, seed and stages in chain order."""

    name: str
    seed: int
    stages: list[StageSpec]
    file: str
    description: str = ""

    def resolved(self) -> dict[str, Any]:
        """Every parameter spelled out, defaults included: what the run really used."""
        chain = []
        for s in self.stages:
            entry: dict[str, Any] = {"use": s.use}
            if s.id != s.use:
                entry["id"] = s.id
            entry.update(s.params.model_dump(mode="json"))
            chain.append(entry)
        out: dict[str, Any] = {"name": self.name, "seed": self.seed}
        if self.description:
            out["description"] = self.description
        out["chain"] = chain
        return out

    def stage(self, key: str) -> StageSpec:
        return _find_stage(self.stages, key, lambda s: (s.id, s.use), Mark(self.file))


def _raise(message: str, mark: Mark, key: str | None = None, cls=ConfigError):
    raise cls(message, file=mark.file, line=mark.line, column=mark.column, key=key)


def _mark_of(node: yaml.Node | None, file: str) -> Mark:
    if node is None:
        return Mark(file)
    return Mark(file, node.start_mark.line + 1, node.start_mark.column + 1)


def _child_nodes(node: yaml.MappingNode) -> dict[Any, tuple[yaml.Node, yaml.Node]]:
    return {k.value: (k, v) for k, v in node.value if isinstance(k, yaml.ScalarNode)}


class _Loader(yaml.SafeLoader):
    """Safe loading without aliases (``*name``): an alias repeats a value, and nested aliases
    expand a file of a few hundred bytes into gigabytes ("billion laughs")."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise ConfigError(f"YAML alias *{event.anchor}: aliases are not allowed in evchain "
                              "files; write the value out", file=self.name,
                              line=event.start_mark.line + 1, column=event.start_mark.column + 1)
        return super().compose_node(parent, index)


def _check_duplicate_keys(root: yaml.Node | None, file: str) -> None:
    """A key given twice in one mapping is an error (YAML loaders keep the last silently)."""
    todo = [root] if root is not None else []
    while todo:
        node = todo.pop()
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, yaml.Node] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    first = seen.get(k.value)
                    if first is not None:
                        raise ConfigError(f"given twice (first on line "
                                          f"{first.start_mark.line + 1}); keep one",
                                          file=file, line=k.start_mark.line + 1,
                                          column=k.start_mark.column + 1, key=str(k.value))
                    seen[k.value] = k
                todo += [k, v]
        elif isinstance(node, yaml.SequenceNode):
            todo += node.value


def parse_yaml(text: str, file: str) -> tuple[Any, yaml.Node | None]:
    """Safe-load ``text`` keeping the node tree for line numbers; refuses aliases and keys
    given twice."""
    try:
        loader = _Loader(text)
        loader.name = file
        try:
            node = loader.get_single_node()
            _check_duplicate_keys(node, file)
            data = loader.construct_document(node) if node is not None else None
        finally:
            loader.dispose()
    except yaml.MarkedYAMLError as exc:
        m = exc.problem_mark
        raise ConfigError(f"not valid YAML: {exc.problem}", file=file,
                          line=m.line + 1 if m else None,
                          column=m.column + 1 if m else None) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML: {exc}", file=file) from None
    return data, node


def load_pipeline(path: str | Path, registry: Registry, overrides: list[str] = (),
                  set_dir: str | Path | None = None) -> PipelineSpec:
    """Read, validate and wire a pipeline file, applying ``--set`` overrides; input files are
    relative to the file's folder (those of ``overrides``: to ``set_dir``, default the current
    folder)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError("pipeline file not found", file=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read pipeline file: {exc}", file=str(path)) from None
    return pipeline_from_text(text, str(path), registry, overrides, base_dir=path.parent,
                              set_dir=set_dir)


def pipeline_from_text(text: str, file: str, registry: Registry, overrides: list[str] = (),
                       base_dir: str | Path | None = None,
                       set_dir: str | Path | None = None) -> PipelineSpec:
    """A validated pipeline from YAML text; relative input files in the text are resolved
    against ``base_dir`` and those of ``overrides`` against ``set_dir`` (both default: the
    current folder)."""
    data, node = parse_yaml(text, file)
    raw_stages, name, seed, description = _check_shape(data, node, file)
    for item in overrides:
        seed = _apply_override(item, raw_stages, seed)
    stages, problems = [], []
    for raw in raw_stages:
        try:
            stages.append(_validate_stage(raw, registry))
        except ConfigError as exc:
            problems.append(exc)
    if problems:
        raise _all_of(problems)
    check_wiring(stages, registry)
    check_sensor_size(stages)
    _check_ids(stages)
    stages = _check_files(stages, Path(base_dir or "."), Path(set_dir or "."))
    return PipelineSpec(name=name or Path(file).stem, seed=seed, stages=stages, file=file,
                        description=description)


@dataclass
class _RawStage:
    values: dict[str, Any]
    mark: Mark
    key_marks: dict[str, Mark]


def _check_shape(data, node, file) -> tuple[list[_RawStage], str, int, str]:
    top = Mark(file, 1, 1)
    if not isinstance(data, dict):
        _raise("a pipeline must be a mapping with a 'chain' list of stages", _mark_of(node, file))
    nodes = _child_nodes(node)
    for key in data:
        if key not in TOP_KEYS:
            allowed = ", ".join(f"{k} ({v})" for k, v in TOP_KEYS.items())
            _raise(f"unknown key; allowed: {allowed}", _mark_of(nodes.get(key, (None,))[0], file),
                   str(key))
    if "chain" not in data:
        _raise("missing key 'chain' (a list of stages, each with 'use: FILTER')", top)
    name, seed, description = data.get("name"), data.get("seed", 0), data.get("description", "")
    for key, value, kind in (("name", name, str), ("description", description, str),
                             ("seed", seed, int)):
        if value is not None and (not isinstance(value, kind) or isinstance(value, bool)):
            _raise(f"must be {TOP_KEYS[key]}, got {value!r}", _mark_of(nodes[key][1], file), key)
    chain_node = nodes["chain"][1]
    chain = data["chain"]
    if not isinstance(chain, list) or not chain:
        _raise("must be a non-empty list of stages, each a mapping with 'use: FILTER'",
               _mark_of(chain_node, file), "chain")
    stages = []
    for i, (item, item_node) in enumerate(zip(chain, chain_node.value, strict=True)):
        mark = _mark_of(item_node, file)
        if not isinstance(item, dict):
            _raise("a stage must be a mapping with 'use: FILTER' and its parameters", mark,
                   f"chain[{i}]")
        if "use" not in item:
            _raise("missing key 'use' (the filter's name; see 'evchain filters')", mark,
                   f"chain[{i}]")
        if not isinstance(item["use"], str):
            _raise("'use' must be a filter name", mark, f"chain[{i}].use")
        key_marks = {k: _mark_of(v, file) for k, (_, v) in _child_nodes(item_node).items()}
        stages.append(_RawStage(dict(item), mark, key_marks))
    return stages, name, seed, description


def _all_of(problems: list[ConfigError]) -> ConfigError:
    """One error for several: the first one's place, every message on its own line."""
    problems = [q for p in problems for q in getattr(p, "problems", [p])]
    if len(problems) == 1:
        return problems[0]
    first = problems[0]
    listing = "\n".join(f"  {p}" for p in problems)
    exc = ConfigError(f"{len(problems)} problems:\n{listing}")
    exc.file, exc.line, exc.column, exc.key = first.file, first.line, first.column, first.key
    exc.problems = problems
    return exc


def _validate_stage(raw: _RawStage, registry: Registry) -> StageSpec:
    values = dict(raw.values)
    use = values.pop("use")
    stage_id = str(values.pop("id", use))
    if use not in registry.filters:
        _raise(unknown_filter_message(use, registry.filters), raw.key_marks.get("use", raw.mark),
               f"{stage_id}.use")
    cls = registry.get(use)
    try:
        params = cls.Params(**values)
    except ValidationError as exc:
        raise _all_of([_param_error(err, cls, raw, use, stage_id)
                       for err in exc.errors()]) from None
    return StageSpec(use=use, id=stage_id, cls=cls, params=params, mark=raw.mark,
                     key_marks=raw.key_marks)


def _check_files(stages: list[StageSpec], base_dir: Path, set_dir: Path) -> list[StageSpec]:
    """Stages with their input files made absolute; every missing or unreadable input and
    every output outside the run folder is a problem, all reported at once."""
    problems, out = [], []
    for s in stages:
        updates = {}
        for key in s.cls.input_paths:
            value = getattr(s.params, key)
            if value is None:
                continue
            mark = s.key_marks.get(key, s.mark)
            from_set = mark.file.startswith("--set")
            given = Path(os.path.expanduser(value))
            path = Path(os.path.abspath((set_dir if from_set else base_dir) / given))
            updates[key] = str(path)
            if given.is_absolute():
                relative = ""
            elif from_set:
                relative = " (relative to the current folder)"
            else:
                relative = f" (relative to the folder of {mark.file})"
            if not path.exists():
                problems.append(ConfigError(f"input not found: {path}{relative}", file=mark.file,
                                            line=mark.line, column=mark.column,
                                            key=f"{s.id}.{key}"))
            elif not os.access(path, os.R_OK):
                problems.append(ConfigError(f"input not readable (permission denied): {path}",
                                            file=mark.file, line=mark.line, column=mark.column,
                                            key=f"{s.id}.{key}"))
        for key in s.cls.output_paths:
            value = getattr(s.params, key)
            if value is None:
                continue
            norm = os.path.normpath(value)
            if os.path.isabs(norm) or norm == ".." or norm.startswith(".." + os.sep) or norm == ".":
                mark = s.key_marks.get(key, s.mark)
                problems.append(ConfigError(
                    f"{value!r} must name a file or folder inside the run folder (outputs are "
                    "written there; choose the run folder with --out): give a relative path "
                    f"such as {Path(value).name or 'out'!r}", file=mark.file, line=mark.line,
                    column=mark.column, key=f"{s.id}.{key}"))
        if updates:
            s = dataclasses.replace(s, params=s.params.model_copy(update=updates))
        out.append(s)
    if problems:
        raise _all_of(problems)
    return out


def _param_error(err, cls: type[Filter], raw: _RawStage, use: str, stage_id: str) -> ConfigError:
    """A pydantic error of one parameter as a ConfigError at the parameter's line."""
    key = str(err["loc"][0]) if err["loc"] else None
    mark = raw.key_marks.get(key, raw.mark) if key else raw.mark
    if err["type"] == "extra_forbidden":
        allowed = sorted(cls.Params.model_fields)
        close = difflib.get_close_matches(key, allowed, n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        msg = (f"unknown parameter of filter {use!r}; {hint}allowed: "
               f"{', '.join(allowed) or '(none)'}")
    else:
        msg = f"{err['msg']} (got {err.get('input')!r}); {_describe_field(cls, key)}"
    return ConfigError(msg, file=mark.file, line=mark.line, column=mark.column,
                       key=f"{stage_id}.{key}" if key else stage_id)


def _describe_field(cls: type[Filter], key: str | None) -> str:
    if key is None or key not in cls.Params.model_fields:
        return f"see 'evchain filters {cls.name}'"
    from evchain.core.schema import field_rows

    row = next(r for r in field_rows(cls) if r["name"] == key)
    bounds = f", {row['bounds']}" if row["bounds"] else ""
    return f"expected {row['type']}{bounds}"


def _check_ids(stages: list[StageSpec]) -> None:
    """Every stage has its own name (its ``id``, else its ``use``): overrides, metrics and
    messages address stages by it."""
    seen: dict[str, StageSpec] = {}
    for s in stages:
        first = seen.get(s.id)
        if first is not None:
            where = f"line {first.mark.line}" if first.mark.line else "earlier"
            if s.id == s.use and first.id == first.use:
                _raise(f"a second stage of filter {s.use!r} (the first is at {where}); give "
                       f"each its own 'id:' (e.g. id: {s.use}_2) so that overrides and metrics "
                       "can tell them apart", s.mark, s.id)
            _raise(f"id {s.id!r} is used twice (first at {where}); give each stage its own "
                   "'id:'", s.mark, f"{s.id}.id")
        seen[s.id] = s


def output_type(stages: list[StageSpec], upto: int) -> type[Packet] | None:
    """The packet type stage ``upto`` emits (pass-through filters keep their input's type)."""
    kind = None
    for s in stages[: upto + 1]:
        kind = s.cls.produces or kind
    return kind


def check_wiring(stages: list[StageSpec], registry: Registry) -> None:
    """The first stage is a source, no later one is, each consumes what it is given, and each
    finds the series it needs added by a stage before it (with the dtype it expects)."""
    first = stages[0]
    if not first.cls.is_source():
        _raise(f"the first stage must be a source (a filter that consumes nothing), but "
               f"{first.use!r} consumes {first.cls.consumes.__name__}", first.mark,
               f"{first.id}.use", WiringError)
    for i in range(1, len(stages)):
        s, given = stages[i], output_type(stages, i - 1)
        if s.cls.is_source():
            _raise(f"source {s.use!r} can only be the first stage", s.mark, f"{s.id}.use",
                   WiringError)
        if given is None or not issubclass(given, s.cls.consumes):
            _raise(f"{s.use!r} consumes {s.cls.consumes.__name__} but {stages[i - 1].use!r} "
                   f"before it produces {getattr(given, '__name__', 'nothing')}", s.mark,
                   f"{s.id}.use", WiringError)
    _check_series(stages, registry)


def check_sensor_size(stages: list[StageSpec]) -> None:
    """Every stage can take the sensor size that the source's parameters fix (if they do):
    e.g. a writer whose format cannot address so many pixels fails here, before rendering."""
    source = stages[0]
    size = source.cls.sensor_size(source.params)
    if size is None:
        return
    for s in stages[1:]:
        problem = s.cls.check_sensor(s.params, *size)
        if problem:
            _raise(f"stage {s.id!r} ({s.use}): {problem} (the size is set by "
                   f"{source.id}.width and {source.id}.height, line {source.mark.line})",
                   s.mark, f"{source.id}.width")


def _check_series(stages: list[StageSpec], registry: Registry) -> None:
    """Walk the chain keeping the series added so far; a stage's needs must be among them."""
    added: dict[str, tuple[SeriesDef, StageSpec]] = {}
    for s in stages:
        problems = []
        for want in (*s.cls.needs_series, *s.cls.optional_series):
            have = added.get(want.name)
            if have is None:
                if want in s.cls.needs_series:
                    adders = registry.adders(want.name)
                    by = (f"added by {' or '.join(adders)}" if adders
                          else "no installed filter adds it")
                    problems.append(f"needs series {want.name!r} ({by}) but no stage before it "
                                    "adds it")
            elif have[0].dtype != want.dtype:
                other = have[1]
                problems.append(f"reads series {want.name!r} with fields ({want.fields()}) but "
                                f"stage {other.id!r} (line {other.mark.line}) adds it with "
                                f"fields ({have[0].fields()})")
        if problems:
            _raise(f"stage {s.id!r} " + "; and it ".join(problems), s.mark, None, WiringError)
        for series in s.cls.series_added(s.params):
            added[series.name] = (series, s)


def _find_stage(items, key, names, mark):
    hits = [it for it in items if key in names(it)]
    by_id = [it for it in hits if names(it)[0] == key]
    if len(by_id) == 1:
        return by_id[0]
    if len(hits) == 1:
        return hits[0]
    labels = sorted({n for it in items for n in names(it)})
    if not hits:
        raise ConfigError(f"no stage {key!r} in the chain; stages: {', '.join(labels)}",
                          file=mark.file, key=key)
    raise ConfigError(f"{len(hits)} stages use {key!r}; give them 'id:' keys and address one "
                      "by its id", file=mark.file, key=key)


def _apply_override(item: str, stages: list[_RawStage], seed: int) -> int:
    """Apply ``STAGE.PARAM=VALUE`` (or ``seed=N``) to the raw stages; ``STAGE.PARAM+=NUMBER``
    adds to the value the pipeline or an earlier override set. Returns the seed."""
    where = Mark("--set")
    if "=" not in item:
        raise ConfigError(f"override {item!r} must look like STAGE.PARAM=VALUE or seed=N",
                          file="--set")
    target, value_text = item.split("=", 1)
    add = target.endswith("+")
    target = target.removesuffix("+")
    try:
        value = yaml.safe_load(value_text) if value_text.strip() else ""
    except yaml.YAMLError:
        value = value_text
    if add:
        value = _number(value)
        if value is None:
            raise ConfigError(f"override {item!r}: += adds a number, got {value_text!r}",
                              file="--set", key=target)
    if target == "seed":
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(f"seed must be an integer, got {value_text!r}", file="--set")
        return seed + value if add else value
    if "." not in target:
        raise ConfigError(f"override {item!r} must look like STAGE.PARAM=VALUE or seed=N",
                          file="--set")
    stage_key, param = target.split(".", 1)
    raw = _find_stage(stages, stage_key,
                      lambda s: (str(s.values.get("id", s.values["use"])), s.values["use"]), where)
    if param in ("use", "id"):
        raise ConfigError(f"cannot override {param!r} of a stage", file="--set", key=target)
    if add:
        old = _number(raw.values.get(param))
        if old is None:
            now = raw.values.get(param)
            raise ConfigError(f"override {item!r}: += adds to a number set before (in the "
                              f"pipeline or an earlier override), but {target} is "
                              f"{'not set' if param not in raw.values else repr(now)}",
                              file="--set", key=target)
        value = old + value
    raw.values[param] = value
    raw.key_marks[param] = Mark(f"--set {item}")
    return seed


def _number(value: object) -> int | float | None:
    """``value`` as an int or float (YAML reads ``1e-3`` as a string), else None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int | float):
        return value
    try:
        return float(value) if isinstance(value, str) else None
    except ValueError:
        return None
