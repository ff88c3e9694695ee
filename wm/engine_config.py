"""The root configuration of a run: the node's (:class:`wm.config.NodeConfig`), those of the
subsystems it builds (SP, the odometry, the map stack), the KD's (how it is opened, flushed
and what its memories keep), the planner's (``wm bg``) and What If's (served by ``wm serve``,
asked by ``wm whatif``), read from and written to YAML (:meth:`EngineConfig.from_yaml`,
:meth:`EngineConfig.to_yaml`; ``wm config --default``).

A module of its own so that what only needs the node's settings (the planner, the client)
does not import SP, the odometry and the maps to read them.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
import warnings
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import yaml

from core.errors import EngineError
from kd_store.config import KDConfig
from maps.stack import StackConfig
from sp.context import SPConfig
from sp.odometry import OdometryConfig
from wm.config import NodeConfig, PlannerConfig, WhatIfConfig


class ConfigError(EngineError, ValueError):
    """A configuration document the engine cannot take: names its file and the dotted key."""


@dataclass(frozen=True)
class MovedKey:
    """A setting that moved to another section: ``old`` and ``new`` dotted keys. A document
    giving ``old`` is read as giving ``new`` (with a FutureWarning) when that keeps what a
    run does: when both give the same value, or, with ``may_set``, when the document does not
    give ``new`` (nothing read ``new`` before the move). Otherwise it is a ConfigError naming
    both keys."""

    old: str
    new: str
    may_set: bool


#: Settings that lived in two sections, now in one (files written before give both):
#: the vehicle was ``whatif.vehicle`` (What If's; ``node.vehicle`` was read by nothing), and
#: What If's horizons ``whatif.horizons_s`` repeated the KD's memory horizons (each level's
#: planning horizon, both read).
MOVED_KEYS = (
    MovedKey("whatif.vehicle", "node.vehicle", may_set=True),
    MovedKey("whatif.horizons_s", "kd.memory.horizons_s", may_set=False),
)


@dataclass(frozen=True)
class EngineConfig:
    """Every setting of a run, one section per subsystem (the defaults are each class's own).

    node:     the node cycle, predictions, value judgment, the vehicle (:class:`NodeConfig`;
              ``vehicle`` is What If's vehicle model too).
    sp:       sensory processing levels 2-5 (:class:`sp.context.SPConfig`).
    odometry: LADAR odometry (:class:`sp.odometry.OdometryConfig`); in the node's odometry
              process (``node.odometry_process``) ``max_threads: 0`` means one thread, since
              that process has the one core the node's process leaves.
    maps:     the map stack: levels, fusion, terrain (:class:`maps.stack.StackConfig`).
    kd:       the knowledge database the run writes: spatial index cell (m), tolerances, map
              tiles batched and cached, short-term memory horizons (s), the promotion rule to
              long-term memory (:class:`kd_store.config.KDConfig`); ``promotion.statuses`` is
              a set, written as a sorted list. ``memory.horizons_s`` is each level's planning
              horizon, What If's too.
    planner:  behavior generation, ``wm bg`` (:class:`wm.config.PlannerConfig`); ``wm bg``
              plans over HTTP, so unless the file or ``--budget-s`` gives ``budget_s`` it
              takes 1 s a cycle, not the in-process planner's 0.2 s (wm.cli.BG_BUDGET_S).
    whatif:   What If rollouts: each level's step (s) and the search margins
              (:class:`wm.config.WhatIfConfig`); ``wm serve``'s What If and IsPathValid, and
              ``wm whatif``. What If reads the vehicle and the horizons from ``node`` and
              ``kd`` (:class:`wm.whatif.WhatIf`).

    Each setting lives in one section. A YAML document gives only the fields it changes,
    nested sections by name: mappings (sections) merge into the defaults, lists and dicts
    replace the default whole. A key that moved (:data:`MOVED_KEYS`) is still read where it
    was when that keeps what a run does.
    """

    node: NodeConfig = field(default_factory=NodeConfig)
    sp: SPConfig = field(default_factory=SPConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    maps: StackConfig = field(default_factory=StackConfig)
    kd: KDConfig = field(default_factory=KDConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    whatif: WhatIfConfig = field(default_factory=WhatIfConfig)

    @classmethod
    def of(cls, config: EngineConfig | NodeConfig | None) -> EngineConfig:
        """``config`` as an engine configuration (a bare NodeConfig with default subsystems)."""
        if config is None:
            return cls()
        return config if isinstance(config, EngineConfig) else cls(node=config)

    @classmethod
    def from_dict(
        cls, doc: Any, source: str = "<dict>", base: EngineConfig | None = None
    ) -> EngineConfig:
        """``base`` (None: the defaults) changed by ``doc`` (parsed YAML; None: nothing
        changed)."""
        base = base or cls()
        return from_document(cls, _moved({} if doc is None else doc, base, source), base, source)

    @classmethod
    def from_yaml(cls, path: str | Path, base: EngineConfig | None = None) -> EngineConfig:
        """``base`` (None: the defaults) changed by the YAML file ``path`` (:class:`ConfigError`
        names the file and the dotted key of an unknown key or a value of the wrong type). A
        command whose own defaults differ from the classes' passes them as ``base``, so that
        a field the file does not give keeps the command's default."""
        text = Path(path).read_text(encoding="utf-8")
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as e:  # one line: the problem and where (PyYAML's text spans
            # several, with the line quoted)
            mark = getattr(e, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
            what = getattr(e, "problem", None) or str(e).splitlines()[0]
            raise ConfigError(f"{path}: not a YAML document: {what}{where}") from None
        return cls.from_dict(doc, str(path), base)

    def to_dict(self) -> dict[str, Any]:
        """Every field, as plain YAML values (enums by value, tuples as lists, sets as sorted
        lists)."""
        return to_document(self)

    def to_yaml(self, path: str | Path | None = None) -> str:
        """The whole configuration as YAML text (written to ``path`` as well, if given)."""
        text = (
            "# wm engine configuration (wm.engine_config.EngineConfig); a file may give only the\n"
        )
        text += "# fields it changes, nested sections by name (README: Configuration)\n"
        text += yaml.dump(self.to_dict(), Dumper=_Dumper, sort_keys=False, width=120)
        if path is not None:
            Path(path).write_text(text, encoding="utf-8")
        return text


_ABSENT = object()


def _at(doc: Any, key: str) -> Any:
    """The value at dotted ``key`` of the mapping ``doc`` (_ABSENT when not there)."""
    for part in key.split("."):
        if not isinstance(doc, dict) or part not in doc:
            return _ABSENT
        doc = doc[part]
    return doc


def _typed_default(base: Any, key: str) -> tuple[Any, Any]:
    """(type hint, value of ``base``) of the field at dotted ``key`` of the dataclass ``base``."""
    *parents, name = key.split(".")
    for part in parents:
        base = getattr(base, part)
    return typing.get_type_hints(type(base))[name], getattr(base, name)


def _moved(doc: Any, base: EngineConfig, source: str) -> Any:
    """``doc`` with each key that moved (:data:`MOVED_KEYS`) read at its new place, a
    FutureWarning saying so; a ConfigError where reading it there would change what a run
    does. ``doc`` itself is not changed."""
    if not isinstance(doc, dict):
        return doc
    for moved in MOVED_KEYS:
        value = _at(doc, moved.old)
        if value is _ABSENT:
            continue
        tp, default = _typed_default(base, moved.new)
        was = from_document(tp, value, default, source, moved.old)
        given = _at(doc, moved.new)
        now = default if given is _ABSENT else from_document(tp, given, default, source, moved.new)
        if was != now and not (given is _ABSENT and moved.may_set):
            whose = "this file's" if given is not _ABSENT else "the default"
            raise ConfigError(
                f"{source}: {moved.old}: this setting lives in {moved.new} alone now, and "
                f"{whose} {moved.new} differs ({now!r}); give the value there and remove "
                f"{moved.old}"
            )
        doc = _without(doc, moved.old.split("."))
        if given is _ABSENT and was != now:
            doc = _with(doc, moved.new.split("."), value)
        warnings.warn(
            f"{source}: {moved.old} is read as {moved.new}, where this setting lives now; "
            f"give it there and remove {moved.old}",
            FutureWarning,
            stacklevel=3,
        )
    return doc


def _without(doc: dict, path: list[str]) -> dict:
    """A copy of ``doc`` without the key at ``path`` (copies along the path only)."""
    out = dict(doc)
    if len(path) == 1:
        del out[path[0]]
    else:
        out[path[0]] = _without(doc[path[0]], path[1:])
    return out


def _with(doc: dict, path: list[str], value: Any) -> dict:
    """A copy of ``doc`` with ``value`` at ``path`` (missing sections made; copies along the
    path only). A section that is not a mapping is left for :func:`from_document` to name."""
    out = dict(doc)
    if len(path) == 1:
        out[path[0]] = value
        return out
    sub = doc.get(path[0], {})
    if isinstance(sub, dict):
        out[path[0]] = _with(sub, path[1:], value)
    return out


class _Dumper(yaml.SafeDumper):
    """Sections as blocks; a list of plain values on one line (``[0.25, 0.5, 1.0]``), and
    each item of a list that is a mapping of plain values (a map layer) on one line."""


class _FlowMap(dict):
    pass


def _plain(values: Any) -> bool:
    return all(not isinstance(v, dict | list) for v in values)


def _represent_list(dumper: yaml.SafeDumper, data: list) -> yaml.Node:
    items = [_FlowMap(v) if isinstance(v, dict) and _plain(v.values()) else v for v in data]
    return dumper.represent_sequence("tag:yaml.org,2002:seq", items, flow_style=_plain(data))


_Dumper.add_representer(list, _represent_list)
_Dumper.add_representer(
    _FlowMap, lambda d, m: d.represent_mapping("tag:yaml.org,2002:map", m, flow_style=True)
)


def to_document(value: Any) -> Any:
    """A (nested) configuration value as plain YAML values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_document(getattr(value, f.name)) for f in dataclasses.fields(value) if f.init
        }
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, tuple | list):
        return [to_document(v) for v in value]
    if isinstance(value, frozenset | set):  # YAML has no set; sorted, so the text is stable
        return sorted(to_document(v) for v in value)
    if isinstance(value, dict):
        return {to_document(k): to_document(v) for k, v in value.items()}
    return value


def from_document(tp: Any, value: Any, default: Any, source: str, key: str = "") -> Any:
    """``value`` (parsed YAML) as type ``tp``: a dataclass from a mapping of (some of) its
    fields, merged into ``default`` (or the class's defaults when ``default`` is not one);
    tuples and (frozen) sets from lists, dicts, enums by value, Optional, bool, int, float (an
    int or a number's text too), str. ``key`` is the dotted key so far, for
    :class:`ConfigError`."""

    def bad(what: str) -> ConfigError:
        return ConfigError(f"{source}: {key or '(top level)'}: {what}")

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise bad(f"expected a mapping of {tp.__name__} fields, got {value!r}")
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
        base = default if isinstance(default, tp) else None
        changes = {}
        for k, v in value.items():
            sub = f"{key}.{k}" if key else str(k)
            if k not in fields:
                near = difflib.get_close_matches(str(k), fields, n=3)
                hint = (
                    f"did you mean {' or '.join(near)}?" if near else f"known: {', '.join(fields)}"
                )
                raise ConfigError(f"{source}: {sub}: unknown key of {tp.__name__}; {hint}")
            d = getattr(base, k) if base is not None else None
            changes[k] = from_document(hints[k], v, d, source, sub)
        try:  # the class's own checks (__post_init__), a required field not given
            return dataclasses.replace(base, **changes) if base is not None else tp(**changes)
        except (TypeError, ValueError) as e:
            raise bad(str(e)) from None
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in sorted(args, key=lambda a: a is not type(value)):  # an exact match first
            if a is not type(None):
                try:
                    return from_document(a, value, default, source, key)
                except ConfigError:
                    pass
        raise bad(f"expected {tp}, got {value!r}")
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise bad(f"expected a list, got {value!r}")
        each = [args[0]] * len(value) if args[1:] == (Ellipsis,) else list(args)
        if len(each) != len(value):
            raise bad(f"expected {len(each)} items, got {len(value)}: {value!r}")
        return tuple(
            from_document(t, v, None, source, f"{key}[{i}]")
            for i, (t, v) in enumerate(zip(each, value, strict=True))
        )
    if origin in (frozenset, set):
        if not isinstance(value, list | tuple):
            raise bad(f"expected a list, got {value!r}")
        return origin(
            from_document(args[0], v, None, source, f"{key}[{i}]") for i, v in enumerate(value)
        )
    if origin is dict:
        if not isinstance(value, dict):
            raise bad(f"expected a mapping, got {value!r}")
        return {
            from_document(args[0], k, None, source, f"{key}.{k}"): from_document(
                args[1], v, None, source, f"{key}.{k}"
            )
            for k, v in value.items()
        }
    if isinstance(tp, type) and issubclass(tp, Enum):
        try:
            return tp(value)
        except ValueError:
            raise bad(f"expected one of {[m.value for m in tp]}, got {value!r}") from None
    if tp not in (bool, int, float, str):
        raise bad(f"cannot read a value of type {tp}")
    if tp is float and isinstance(value, int | float | str) and not isinstance(value, bool):
        try:  # text too: YAML 1.1 reads 1e-4 (no dot) as a string
            x = float(value)
        except ValueError:
            pass
        else:  # one NaN object (math.nan, as maps.layers'), so equal configs compare equal
            return math.nan if math.isnan(x) else x
    elif type(value) is tp:
        return value
    raise bad(f"expected {tp.__name__}, got {value!r}")
