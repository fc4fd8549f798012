"""Read a node's private parameters once, into a frozen dataclass.

Every node declares its parameters as a frozen dataclass whose fields have defaults; the field
name is the parameter name (``~<name>``), the default's type is the expected type, and the
field's ``metadata={"doc": "..."}`` (optional) says what it means. :func:`read_params` reads
them all at start-up, so no algorithm ever calls ``rospy.get_param``::

    @dataclass(frozen=True)
    class MapperParams:
        map_file: str = field(default="", metadata={"doc": "where ~save_map writes (YAML)"})
        slop: float = 0.03

    params = read_params(MapperParams)        # inside the node, after rospy.init_node

Coercion (:func:`params_from_dict`, pure, testable without a master): ints are accepted where
floats are expected; bools must be real booleans (a YAML ``"false"`` string is an error, not
``True``); lists/dicts are passed through; ``None`` defaults accept anything. A wrong type
raises :class:`ConfigError` naming the parameter, the expected type and the value given.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Mapping, Optional, Type, TypeVar

from ..errors import ConfigError

P = TypeVar("P")


def _coerce(name: str, value: Any, default: Any, source: str) -> Any:
    if default is None:
        return value
    if isinstance(default, bool):
        if isinstance(value, bool):
            return value
        raise ConfigError(f"expected true or false, got {value!r}", path=source, key=name)
    if isinstance(default, int):
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"expected an integer, got {value!r}", path=source, key=name)
    if isinstance(default, float):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        raise ConfigError(f"expected a number, got {value!r}", path=source, key=name)
    if isinstance(default, str):
        if isinstance(value, str):
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return str(value)  # e.g. a size override "0.05" read back by YAML as a float
        raise ConfigError(f"expected a string, got {value!r}", path=source, key=name)
    if isinstance(default, (list, tuple)):
        if isinstance(value, (list, tuple)):
            return tuple(value)
        if isinstance(value, str):
            return tuple(v for v in value.replace(",", " ").split() if v)
        raise ConfigError(f"expected a list, got {value!r}", path=source, key=name)
    return value


def params_from_dict(cls: Type[P], values: Mapping[str, Any], source: str = "parameters") -> P:
    """Build ``cls`` (a dataclass with defaults) from ``values``; missing names keep their default.

    Raises:
        ConfigError: a value has the wrong type (names the parameter and the value).
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    kwargs: Dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in values:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = f.default_factory()  # type: ignore[misc]
        else:
            default = None
        kwargs[f.name] = _coerce(f.name, values[f.name], default, source)
    return cls(**kwargs)  # type: ignore[call-arg]


def describe(cls: Type[Any]) -> Dict[str, str]:
    """``{parameter: doc}`` from the fields' ``metadata["doc"]`` (for logs and docs)."""
    return {f.name: str(f.metadata.get("doc", "")) for f in dataclasses.fields(cls)}


def read_params(cls: Type[P], namespace: str = "~", overrides: Optional[Mapping[str, Any]] = None) -> P:
    """Read every field of ``cls`` from the parameter server under ``namespace`` (default private).

    Only parameters that are set are read; the others keep the dataclass defaults.
    ``overrides`` (tests) win over the server. Needs ``rospy.init_node`` first.
    """
    import rospy  # imported here so that the pure coercion above is usable without ROS

    values: Dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        key = namespace + f.name if namespace.endswith(("~", "/")) else f"{namespace}/{f.name}"
        if rospy.has_param(key):
            values[f.name] = rospy.get_param(key)
    values.update(overrides or {})
    return params_from_dict(cls, values, source=f"parameters of {rospy.get_name()}")


def read_config(cls: Type[P], namespace: str = "~", overrides: Optional[Mapping[str, Any]] = None) -> P:
    """Read a node's nested schema (:mod:`aruco_ring_localization.config`) from the parameter server.

    The whole private namespace is read at once (``rospy.get_param('~')``: the nested dict that
    ``<rosparam command="load" file="config/NODE.yaml"/>`` and the launch file's overrides made);
    unknown keys are warned about once each, by name (``rospy.logwarn``). ``overrides`` (dotted
    keys, tests) win. Needs ``rospy.init_node`` first.
    """
    import rospy

    from ..config import load_config, to_dict, with_overrides

    values = rospy.get_param(namespace, {}) if rospy.has_param(namespace) else {}
    source = f"parameters of {rospy.get_name()}"
    config = load_config(cls, values, source=source, warn=rospy.logwarn)
    if overrides:
        config = with_overrides(config, overrides, source="overrides")
    rospy.logdebug("%s: %s", source, to_dict(config))
    return config
