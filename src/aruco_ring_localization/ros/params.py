"""Read a node's private parameters once, into its schema (no algorithm ever calls ``rospy.get_param``).

:func:`read_config` reads the node's nested schema (:mod:`aruco_ring_localization.schemas`, built
with :mod:`aruco_ring_localization.config`) from its private namespace: the nested dict that
``<rosparam command="load" file="config/NODE.yaml"/>`` and the launch file's overrides made::

    config = read_config(LocalizerConfig)      # inside the node, after rospy.init_node

Unknown keys are warned about once each, by their dotted name; a value of the wrong type raises
:class:`ConfigError` naming the key. :func:`read_params` is the older flat form (only the fields
of a flat dataclass are read, nothing is warned about), kept for the simulator.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Dict, Mapping, Optional, Type, TypeVar

from ..config import coerce

P = TypeVar("P")


def params_from_dict(cls: Type[P], values: Mapping[str, Any], source: str = "parameters") -> P:
    """Build the flat dataclass ``cls`` from ``values``; missing names keep their default.

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
        kwargs[f.name] = coerce(f.name, values[f.name], default, source)
    return cls(**kwargs)  # type: ignore[call-arg]


def read_params(cls: Type[P], namespace: str = "~", overrides: Optional[Mapping[str, Any]] = None) -> P:
    """Read every field of the flat dataclass ``cls`` from the parameter server under ``namespace``.

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
    """Read a node's nested schema from the parameter server (the whole private namespace at once).

    Unknown keys are warned about once each, by name (``rospy.logwarn``). ``overrides`` (dotted
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
