"""Reading, overriding, validating and writing scenario files.

Every failure is a :class:`ScenarioError` whose message is one line that starts with the field at
fault (``subsystems[2].A: expected a 2x2 matrix, got 2x3``) or, for problems with the file as a
whole, with the file's path.
"""
from __future__ import annotations

import copy
import difflib
import re
import types
from pathlib import Path
from typing import Annotated, Any, Mapping, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError

from dmpc.core.errors import InputError
from dmpc.scenario.schema import SET_TAGS, Scenario, SpecError

__all__ = ["ScenarioError", "dump_resolved", "load_scenario", "parse_override", "scenario_json_schema",
           "validate_scenario"]

MAX_NODES = 1_000_000
"""Largest accepted number of YAML values after expanding aliases (guards against alias bombs)."""


class ScenarioError(InputError):
    """An invalid scenario file, override or value; the message is one line naming the field.

    Attributes
    ----------
    field : str or None
        The dotted/indexed path of the field at fault (e.g. ``subsystems[1].Q``), None for file-level errors.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(" ".join(message.split("\n")))
        self.field = field


class _Loader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that also rejects duplicate keys in a mapping (instead of keeping the last)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    duplicate = key in seen
                    seen.add(key)
                except TypeError:  # unhashable: the base class reports it
                    continue
                if duplicate:
                    raise yaml.constructor.ConstructorError(
                        None, None, f"duplicate key {key!r} (each key may appear once per mapping)",
                        key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


# YAML 1.1 (PyYAML) reads 1e-6 as a string; accept YAML 1.2 exponent floats without a dot as well.
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """``line L, column C: problem`` on one line; python/custom tags get a clear explanation."""
    mark = getattr(exc, "problem_mark", None)
    problem = " ".join(str(getattr(exc, "problem", None) or exc).split())
    tag = re.search(r"for the tag '([^']*)'", problem)
    if isinstance(exc, yaml.constructor.ConstructorError) and tag:
        name = tag.group(1).replace("tag:yaml.org,2002:", "!!")
        problem = f"YAML tag '{name}' is not allowed (plain YAML only: no python/ or custom tags)"
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return where + problem


def _parse_yaml(text: str, source: str) -> Any:
    try:
        return yaml.load(text, Loader=_Loader)  # a SafeLoader subclass: no arbitrary objects
    except yaml.constructor.ConstructorError as exc:
        raise ScenarioError(f"{source}: {_yaml_problem(exc)}") from None
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{source}: not valid YAML ({_yaml_problem(exc)})") from None
    except RecursionError:
        raise ScenarioError(f"{source}: YAML nested too deeply") from None


def _check_size(data: Any, source: str) -> None:
    """Reject recursive aliases and alias bombs (counting shared values once per use)."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(obj: Any) -> int:
        if not isinstance(obj, (dict, list)):
            return 1
        key = id(obj)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise ScenarioError(f"{source}: recursive YAML alias (a value that contains itself)")
        active.add(key)
        items = list(obj.keys()) + list(obj.values()) if isinstance(obj, dict) else obj
        total = 1
        for item in items:
            total += size(item)
            if total > MAX_NODES:
                raise ScenarioError(f"{source}: too large (more than {MAX_NODES} values after expanding aliases)")
        active.discard(key)
        sizes[key] = total
        return total

    try:
        size(data)
    except RecursionError:
        raise ScenarioError(f"{source}: YAML nested too deeply") from None


def load_scenario(path: str | Path, overrides: Mapping[str, object] | None = None) -> Scenario:
    """Read, override and validate a scenario file.

    Parameters
    ----------
    path : str or Path
        A YAML file (plain YAML only; duplicate keys are an error).
    overrides : mapping of dotted path -> value, optional
        Applied to the raw YAML before validation, e.g. ``{"family.M": 8, "options.iterations": 3}``.

    Returns
    -------
    Scenario

    Raises
    ------
    ScenarioError
        For any problem: unreadable or non-YAML file, bad override path, invalid content.
    """
    source = str(path)
    try:
        raw = Path(path).read_bytes()
    except OSError as exc:
        raise ScenarioError(f"{source}: cannot read the file ({exc.strerror or exc})") from None
    if b"\x00" in raw:
        raise ScenarioError(f"{source}: not a YAML text file (contains NUL bytes)")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ScenarioError(f"{source}: not a UTF-8 text file (invalid byte at offset {exc.start})") from None
    data = _parse_yaml(text, source)
    if data is None:
        raise ScenarioError(f"{source}: the file is empty (expected a YAML mapping of scenario fields)")
    return _files_from(validate_scenario(data, overrides, source=source), Path(path).parent)


def _files_from(scn: Scenario, folder: Path) -> Scenario:
    """``scn`` with a relative ``plant.disturbance.file`` made absolute against ``folder`` (the
    scenario file's), so that the resolved scenario in a run folder still finds it."""
    spec = scn.plant.disturbance
    if spec is None or spec.file is None or Path(spec.file).is_absolute():
        return scn
    absolute = str((folder / spec.file).resolve())
    plant = scn.plant.model_copy(update={"disturbance": spec.model_copy(update={"file": absolute})})
    return scn.model_copy(update={"plant": plant})


def validate_scenario(data: Any, overrides: Mapping[str, object] | None = None,
                      source: str = "<scenario>") -> Scenario:
    """Validate an already parsed scenario mapping (as :func:`load_scenario` does after reading).

    Parameters
    ----------
    data : dict
        The raw mapping; it is not modified.
    overrides : mapping of dotted path -> value, optional
    source : str
        Used in messages about the top level.

    Returns
    -------
    Scenario
    """
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: expected a YAML mapping of scenario fields at the top level, "
                            f"got {type(data).__name__}")
    _check_size(data, source)
    data = copy.deepcopy(data)
    paths = []
    for key, value in (overrides or {}).items():
        paths.append(_apply_override(data, key, value))
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        field, message = _first_error(exc)
        origin = next((p for p in paths if field == p or field.startswith((p + ".", p + "["))), None)
        if origin is not None:
            message += f" (value set by override {origin})"
        raise ScenarioError(f"{field}: {message}" if field else message, field=field) from None
    except RecursionError:
        raise ScenarioError(f"{source}: YAML nested too deeply") from None


# --- error locations ---------------------------------------------------------------------------------

def _format_loc(loc: tuple) -> str:
    out = ""
    for seg in loc:
        if isinstance(seg, int):
            out += f"[{seg}]"
        else:
            out += f".{seg}" if out else str(seg)
    return out


def _join(base: str, rel: str) -> str:
    if not rel:
        return base
    if not base:
        return rel.removeprefix(".")
    if rel.startswith(("[", ".")):
        return base + rel
    return f"{base}.{rel}"


def _clean_loc(loc: tuple) -> tuple:
    """Drop the union tags pydantic inserts after ``input``/``state``."""
    out: list = []
    for seg in loc:
        if seg in SET_TAGS and out and out[-1] in ("input", "state"):
            continue
        out.append(seg)
    return tuple(out)


def _first_error(exc: ValidationError) -> tuple[str, str]:
    err = exc.errors()[0]
    loc = _clean_loc(err["loc"])
    cause = (err.get("ctx") or {}).get("error")
    if isinstance(cause, SpecError):
        return _join(_format_loc(loc), cause.path), cause.message
    kind, value = err["type"], err.get("input")
    if kind == "missing":
        return _format_loc(loc), "required field is missing"
    if kind == "extra_forbidden":
        allowed = _field_names(_walk(loc[:-1]))
        close = difflib.get_close_matches(str(loc[-1]), allowed, n=1)
        hint = f"did you mean '{close[0]}'? " if close else ""
        return _format_loc(loc), f"unknown field ({hint}allowed here: {', '.join(allowed)})"
    message = err["msg"].removeprefix("Value error, ")
    message = message[:1].lower() + message[1:]
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        message = "expected a mapping of fields"
    if not isinstance(value, (dict, list)):
        message += f", got {_show(value)}"
    return _format_loc(loc), message


def _show(value: object) -> str:
    text = repr(value).replace("\n", " ")
    return text if len(text) <= 40 else text[:37] + "..."


# --- walking the schema ------------------------------------------------------------------------------

def _unwrap(tp: Any) -> list:
    """The concrete alternatives of an annotation (Annotated, Optional and unions removed)."""
    origin = get_origin(tp)
    if origin is Annotated:
        return _unwrap(get_args(tp)[0])
    if origin in (Union, types.UnionType):
        return [c for arg in get_args(tp) for c in _unwrap(arg)]
    if tp is type(None):
        return []
    return [tp]


def _is_model(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _step(candidates: list, seg: str | int) -> list:
    """The types reachable from ``candidates`` through one path segment."""
    out = []
    for tp in candidates:
        origin, args = get_origin(tp), get_args(tp)
        if _is_model(tp):
            if isinstance(seg, str) and seg in tp.model_fields:
                out += _unwrap(tp.model_fields[seg].annotation)
        elif origin is list and isinstance(seg, int):
            out += _unwrap(args[0])
        elif origin is tuple and isinstance(seg, int):
            if len(args) == 2 and args[1] is Ellipsis:
                out += _unwrap(args[0])
            elif seg < len(args):
                out += _unwrap(args[seg])
        elif origin is dict and isinstance(seg, str):
            out += _unwrap(args[1])
    return out


def _walk(loc: tuple) -> list:
    candidates: list = [Scenario]
    for seg in loc:
        candidates = _step(candidates, seg)
    return candidates


def _field_names(candidates: list) -> list[str]:
    names: list[str] = []
    for tp in candidates:
        if _is_model(tp):
            names += [n for n in tp.model_fields if n not in names]
    return names


# --- overrides ---------------------------------------------------------------------------------------

_SEGMENT = re.compile(r"^([^.\[\]]+)((?:\[\d+\])*)$")


def _split_path(key: str) -> list[str | int]:
    """``"subsystems[1].x0"`` or ``"subsystems.1.x0"`` -> ``["subsystems", "1", "x0"]`` (brackets -> int)."""
    segs: list[str | int] = []
    for part in key.split("."):
        match = _SEGMENT.match(part.strip())
        if not match:
            raise ScenarioError(f"{key}: invalid override path (use dotted names, e.g. family.M or "
                                "subsystems[0].x0)", field=key)
        segs.append(match.group(1))
        segs += [int(i) for i in re.findall(r"\[(\d+)\]", match.group(2))]
    return segs


def _apply_override(data: dict, key: str, value: object) -> str:
    """Set ``value`` at the dotted ``key`` of the raw mapping, checking the path against the schema.

    Returns
    -------
    str
        The normalised path (``subsystems[1].x0``), used to annotate errors in the value.
    """
    segs = _split_path(key)
    candidates: list = [Scenario]
    for depth, seg in enumerate(segs):
        is_list = any(get_origin(c) in (list, tuple) for c in candidates)
        if is_list and isinstance(seg, str) and seg.isdigit():
            seg = segs[depth] = int(seg)
        nxt = _step(candidates, seg)
        if not nxt:
            where = _format_loc(tuple(segs[:depth + 1]))
            fields = _field_names(candidates)
            if fields:
                hint = f"; fields here: {', '.join(fields)}"
            elif isinstance(seg, str) and any(get_origin(c) in (list, tuple) for c in candidates):
                hint = "; a list needs an index here, e.g. subsystems[0].x0"
            else:
                hint = ""
            raise ScenarioError(f"{where}: no such field in the scenario schema (override '{key}'){hint}",
                                field=where)
        candidates = nxt
    node: Any = data
    for depth, seg in enumerate(segs):
        where = _format_loc(tuple(segs[:depth + 1]))
        last = depth == len(segs) - 1
        if isinstance(node, dict):
            if isinstance(seg, str) and seg not in node and seg.isdigit() and int(seg) in node:
                seg = int(seg)  # a YAML integer key such as alpha0: {1: [...]}
            if last:
                node[seg] = value
            else:
                if node.get(seg) is None:
                    if isinstance(segs[depth + 1], int):
                        raise ScenarioError(f"{where}: no list to index in the file (override '{key}')",
                                            field=where)
                    node[seg] = {}
                node = node[seg]
        elif isinstance(node, list) and isinstance(seg, int):
            if seg >= len(node):
                raise ScenarioError(f"{where}: index out of range, the list has {len(node)} entries "
                                    f"(override '{key}')", field=where)
            if last:
                node[seg] = value
            else:
                node = node[seg]
        else:
            parent = _format_loc(tuple(segs[:depth])) or "top level"
            raise ScenarioError(f"{parent}: cannot set '{seg}' inside a {type(node).__name__} "
                                f"(override '{key}')", field=parent)
    return _format_loc(tuple(segs))


def parse_override(text: str) -> tuple[str, object]:
    """Split ``"family.M=8"`` into ``("family.M", 8)``; the value is parsed as YAML.

    Parameters
    ----------
    text : str
        ``KEY=VALUE``; VALUE may be any plain YAML (``3``, ``lmi``, ``[1, 2]``, ``null``).

    Returns
    -------
    (str, object)
    """
    key, sep, raw = text.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ScenarioError(f"override {text!r}: expected KEY=VALUE, e.g. family.M=8")
    _split_path(key)
    try:
        value = yaml.load(raw, Loader=_Loader)  # a SafeLoader subclass: no arbitrary objects
    except yaml.YAMLError as exc:
        raise ScenarioError(f"{key}: override value {raw!r} is not valid YAML ({_yaml_problem(exc)})",
                            field=key) from None
    except RecursionError:
        raise ScenarioError(f"{key}: override value nested too deeply", field=key) from None
    return key, value


# --- schema and dump ---------------------------------------------------------------------------------

def scenario_json_schema() -> dict:
    """The JSON Schema of scenario files (generated from the pydantic models)."""
    schema = Scenario.model_json_schema()
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **schema}


class _Dumper(yaml.SafeDumper):
    """Safe dumper writing vectors and matrices in flow style (``[[1.0, 0.0], [0.0, 1.0]]``)."""


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    def scalar(x: object) -> bool:
        return not isinstance(x, (dict, list, tuple))

    flow = all(scalar(x) or (isinstance(x, (list, tuple)) and all(scalar(y) for y in x)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", list(data), flow_style=flow)


_Dumper.add_representer(list, _represent_list)
_Dumper.add_representer(tuple, _represent_list)


def dump_resolved(scn: Scenario) -> str:
    """YAML text of the validated scenario with every default filled in.

    The family (if any) is kept, not expanded, so that ``load_scenario`` of the text gives a
    model equal to ``scn``.
    """
    data = scn.model_dump(mode="python")
    for key in ("subsystems", "family"):
        if data[key] is None:
            del data[key]
    header = "# Resolved scenario: every field with its value, defaults filled in.\n"
    # allow_unicode=False: PyYAML cannot read back some characters it writes raw (e.g. U+0085)
    return header + yaml.dump(data, Dumper=_Dumper, sort_keys=False, allow_unicode=False, width=110)
