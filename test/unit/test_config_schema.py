"""The parameter-schema mechanism (config.py): nested sections, coercion, unknown keys, errors."""
from __future__ import annotations

from dataclasses import dataclass

import pytest

from aruco_ring_localization.config import flatten, load_config, param, section, to_dict, with_overrides
from aruco_ring_localization.errors import ConfigError


@dataclass(frozen=True)
class _Inner:
    """Inner section."""

    distance: float = param(0.15, "allowed jump", unit="m")
    count: int = param(5, "how many")
    enabled: bool = param(True, "on or off")

    def __post_init__(self) -> None:
        if not self.distance > 0:
            raise ConfigError(f"must be positive, got {self.distance!r}", key="distance")


@dataclass(frozen=True)
class _Outer:
    name: str = param("joint", "a word")
    cameras: tuple = param([], "names")
    inner: _Inner = section(_Inner)


def test_defaults_and_nested_values():
    c = load_config(_Outer, {"name": "paper", "inner": {"distance": 1, "count": 3}})
    assert c.name == "paper" and c.inner.distance == 1.0 and isinstance(c.inner.distance, float)
    assert c.inner.count == 3 and c.inner.enabled is True and c.cameras == ()
    assert load_config(_Outer, None) == _Outer()


def test_lists_from_yaml_or_a_launch_string():
    assert load_config(_Outer, {"cameras": ["cam0", "cam1"]}).cameras == ("cam0", "cam1")
    assert load_config(_Outer, {"cameras": "cam0, cam1 cam2"}).cameras == ("cam0", "cam1", "cam2")


def test_unknown_keys_are_named_with_their_path():
    said = []
    load_config(_Outer, {"nmae": 1, "inner": {"distanse": 2.0}}, source="f.yaml", warn=said.append)
    assert len(said) == 2
    assert "'nmae'" in said[0] and "f.yaml" in said[0]
    assert "'inner.distanse'" in said[1]


@pytest.mark.parametrize("values, key", [
    ({"inner": {"enabled": "false"}}, "inner.enabled"),   # a string is not a bool
    ({"inner": {"count": 2.5}}, "inner.count"),
    ({"inner": {"distance": "far"}}, "inner.distance"),
    ({"inner": {"distance": -1.0}}, "inner.distance"),    # refused by __post_init__
    ({"inner": 3}, "inner"),                              # a section must be a mapping
    ({"name": [1]}, "name"),
])
def test_errors_name_the_dotted_key_and_the_source(values, key):
    with pytest.raises(ConfigError) as err:
        load_config(_Outer, values, source="params.yaml")
    assert err.value.key == key, str(err.value)
    assert "params.yaml" in str(err.value)


def test_flatten_to_dict_and_overrides_round_trip():
    keys = {k: (d, u) for k, d, _, u in flatten(_Outer)}
    assert keys["inner.distance"] == (0.15, "m") and keys["cameras"] == ((), "")
    c = with_overrides(_Outer(), {"inner.count": 9, "name": "x"})
    assert c.inner.count == 9 and c.name == "x"
    assert load_config(_Outer, to_dict(c)) == c
