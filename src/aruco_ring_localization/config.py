"""One parameter schema per node: nested frozen dataclasses, each default written once.

A node's schema is a frozen dataclass whose fields are either plain values (with a default) or
sections (fields whose default is another such dataclass, given by ``default_factory``). Every
field documents itself with :func:`param`::

    @dataclass(frozen=True)
    class GateParams:
        base_distance: float = param(0.15, "allowed jump at rest", unit="m")

    @dataclass(frozen=True)
    class LocalizerConfig:
        gate: GateParams = section(GateParams)

The same schema is read from a YAML file (``config/*.yaml``), from the ROS parameter server (the
node's private namespace, a nested dict: ``ros/params.py``) or from command-line options; the
YAML file mirrors it key for key (a test checks names and defaults against the dataclasses, the
launch files and ``docs/parameters.md``). :func:`load_config` coerces each value to its default's
type, warns once about every key the schema does not know (naming it with its dotted path, so a
typo is never silently ignored), and raises :class:`errors.ConfigError` naming the key on a wrong
type or a value the dataclass's ``__post_init__`` refuses.

Units are SI unless the name says otherwise (``_deg``, ``_px``, ``_ms``); :func:`param` records the
unit for the docs.
"""
from __future__ import annotations

import dataclasses
import logging
import math
from typing import Any, Callable, Dict, Iterator, List, Mapping, Optional, Tuple, Type, TypeVar

from .errors import ConfigError

logger = logging.getLogger(__name__)

C = TypeVar("C")


def param(default: Any, doc: str = "", unit: str = "") -> Any:
    """A schema field: its default (written only here), what it means, its unit."""
    if isinstance(default, list):
        default = tuple(default)  # frozen dataclasses hold tuples, YAML gives lists: both accepted
    return dataclasses.field(default=default, metadata={"doc": doc, "unit": unit})


def section(cls: Type[Any], doc: str = "", **defaults: Any) -> Any:
    """A schema field holding a nested schema (a YAML mapping with its own keys).

    ``defaults`` change some of the section's defaults for this use only (the mapper refines the
    ring extrinsics by default, a bare bundle adjustment does not):
    ``ba: BAOptions = section(BAOptions, refine_extrinsics=True)``; the docs, the YAML check and
    :func:`load_config` all start from these values.
    """
    factory = (lambda: cls(**defaults)) if defaults else cls
    return dataclasses.field(default_factory=factory, metadata={
        "doc": doc or (cls.__doc__ or "").strip().split("\n")[0], "section": True})


def in_radians(deg_field: str) -> property:
    """A read-only property of a schema: its field ``deg_field`` (degrees, as people write them) in
    radians (as the code uses them): ``base_angle = in_radians("base_angle_deg")``."""
    return property(lambda self: math.radians(getattr(self, deg_field)), doc=f"``{deg_field}`` in rad.")


def require_positive(config: Any, *names: str) -> None:
    """Raise ConfigError naming the first of the fields ``names`` of ``config`` that is not > 0
    (for a schema's ``__post_init__``; NaN is refused too)."""
    for name in names:
        value = getattr(config, name)
        if not value > 0:
            raise ConfigError(f"must be positive, got {value!r}", key=name)


def _default_of(f: "dataclasses.Field[Any]") -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return None


def is_section(f: "dataclasses.Field[Any]") -> bool:
    return bool(f.metadata.get("section")) or dataclasses.is_dataclass(_default_of(f))


def coerce(key: str, value: Any, default: Any, source: str) -> Any:
    """``value`` as the type of ``default``; raises ConfigError naming ``key`` and ``source``."""
    if default is None:
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        raise ConfigError(f"expected true or false, got {value!r}", path=source, key=key)
    if isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"expected an integer, got {value!r}", path=source, key=key)
    if isinstance(default, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str):
            try:
                return float(value)  # YAML 1.1 reads 1e-8 (no dot) as a string
            except ValueError:
                pass
        raise ConfigError(f"expected a number, got {value!r}", path=source, key=key)
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)  # e.g. a size override "0.05" that YAML read as a float
        raise ConfigError(f"expected a string, got {value!r}", path=source, key=key)
    if isinstance(default, tuple):
        if isinstance(value, (list, tuple)):
            return tuple(value)
        if isinstance(value, str):  # "cam0 cam1" or "cam0, cam1" from a launch argument
            return tuple(v for v in value.replace(",", " ").split() if v)
        raise ConfigError(f"expected a list, got {value!r}", path=source, key=key)
    if isinstance(default, dict):
        if isinstance(value, Mapping):
            return dict(value)
        raise ConfigError(f"expected a mapping, got {value!r}", path=source, key=key)
    return value


def load_config(cls: Type[C], values: Optional[Mapping[str, Any]], source: str = "parameters",
                warn: Optional[Callable[[str], None]] = None, prefix: str = "",
                unknown: Optional[List[str]] = None, base: Optional[C] = None) -> C:
    """Build the schema ``cls`` from a nested mapping; missing keys keep their defaults.

    Args:
        values: nested mapping (YAML document, ``rospy.get_param('~')``); None = all defaults.
        source: named in errors and warnings (a file path, ``parameters of /localizer``).
        warn: called once per unknown key with a message (default: ``logger.warning``).
        prefix, unknown, base: internal (dotted path of the section; list collecting unknown
            keys; the section's default instance, whose values missing keys keep).

    Raises:
        ConfigError: a value of the wrong type, a section that is not a mapping, or a value the
            dataclass refuses; the message names the dotted key.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    warn = warn or logger.warning
    top = unknown is None
    unknown = [] if unknown is None else unknown
    values = {} if values is None else values
    if not isinstance(values, Mapping):
        raise ConfigError(f"expected a mapping of parameters, got {type(values).__name__}", path=source,
                          key=prefix.rstrip(".") or None)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs: Dict[str, Any] = {}
    for name, value in values.items():
        key = f"{prefix}{name}"
        f = fields.get(str(name))
        if f is None:
            unknown.append(key)
            continue
        default = getattr(base, f.name) if base is not None else _default_of(f)
        if is_section(f):
            kwargs[f.name] = load_config(type(default), value, source, warn, prefix=f"{key}.", unknown=unknown,
                                         base=default)
        else:
            kwargs[f.name] = coerce(key, value, default, source)
    try:
        out = dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)  # type: ignore[call-arg]
    except ConfigError as exc:
        # __post_init__ names its own field; say where it sits in the whole schema, and the source.
        key = f"{prefix}{exc.key}" if exc.key else (prefix.rstrip(".") or None)
        raise ConfigError(exc.detail, path=exc.path or source, key=key) from None
    except (TypeError, ValueError) as exc:
        raise ConfigError(str(exc), path=source, key=prefix.rstrip(".") or None) from None
    if top:
        for key in unknown:
            warn(f"{source}: unknown parameter '{key}' ignored (known: see docs/parameters.md)")
    return out


def flatten(cls: Type[Any], prefix: str = "", base: Any = None) -> Iterator[Tuple[str, Any, str, str]]:
    """``(dotted key, default, doc, unit)`` of every plain field of the schema, sections expanded.

    ``cls`` may also be an instance: its values are then the defaults listed.
    """
    if base is None and not isinstance(cls, type):
        base = cls
    for f in dataclasses.fields(cls):
        default = getattr(base, f.name) if base is not None else _default_of(f)
        if is_section(f):
            yield from flatten(type(default), f"{prefix}{f.name}.", base=default)
        else:
            yield f"{prefix}{f.name}", default, str(f.metadata.get("doc", "")), str(f.metadata.get("unit", ""))


def sections(cls: Type[Any], prefix: str = "") -> Iterator[Tuple[str, str]]:
    """``(dotted key, doc)`` of every section of the schema, depth first (for the docs)."""
    for f in dataclasses.fields(cls):
        if is_section(f):
            yield f"{prefix}{f.name}", str(f.metadata.get("doc", ""))
            yield from sections(type(_default_of(f)), f"{prefix}{f.name}.")


def default(cls: Type[Any], name: str) -> Any:
    """The default of field ``name`` of schema ``cls``, for a schema that re-exports one value of
    another under a name of its own (written once: in ``cls``)."""
    for f in dataclasses.fields(cls):
        if f.name == name:
            return _default_of(f)
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def to_dict(config: Any) -> Dict[str, Any]:
    """The nested mapping of a schema instance (tuples as lists), as YAML would hold it."""
    out: Dict[str, Any] = {}
    for f in dataclasses.fields(config):
        v = getattr(config, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = to_dict(v)
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def with_overrides(config: C, overrides: Mapping[str, Any], source: str = "overrides") -> C:
    """A copy of ``config`` with dotted-key overrides applied (``{"gate.base_distance": 0.2}``)."""
    nested: Dict[str, Any] = to_dict(config)
    for dotted, value in overrides.items():
        node = nested
        parts = dotted.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ConfigError("is not a section", path=source, key=dotted)
        node[parts[-1]] = value
    return load_config(type(config), nested, source)


def load_yaml_config(cls: Type[C], path: str, overrides: Optional[Mapping[str, Any]] = None,
                     warn: Optional[Callable[[str], None]] = None) -> C:
    """The schema ``cls`` from a node's YAML file (``config/localization.yaml``) plus dotted-key
    ``overrides`` whose value is not None (command-line options left unset keep the file's value).

    Raises:
        ConfigError: the file cannot be read or parsed, or a value is refused (names the key).
    """
    import yaml

    try:
        with open(path, encoding="utf-8") as fh:
            values = yaml.safe_load(fh)
    except OSError as exc:
        raise ConfigError(f"cannot read the parameter file ({exc.strerror or exc})", path=path) from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"not valid YAML: {exc}", path=path) from None
    config = load_config(cls, values or {}, source=path, warn=warn)
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    return with_overrides(config, given, source=f"{path} + command-line options") if given else config
