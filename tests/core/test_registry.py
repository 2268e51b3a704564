"""The registry every kind of component is found in (stages.core.registry): names in order, a
name taken once, a temporary entry gone after its block even when the block fails, and a
setting typed by it takes its names when a value is checked."""

from __future__ import annotations

import dataclasses
from typing import Annotated

import pytest

from stages.core.errors import ConfigError
from stages.core.registry import Registry
from stages.core.settings import Settings, setting


def test_entries_by_name_in_order_and_a_name_taken_once():
    r = Registry("fruit")
    r.register("pear", 1)
    r.register("apple", 2)
    assert r.names() == tuple(r) == ("pear", "apple") and r.entries() == (1, 2) and r["apple"] == 2
    assert "pear" in r and "plum" not in r and 3 not in r and len(r) == 2
    with pytest.raises(ValueError, match="a fruit named 'pear' is already registered"):
        r.register("pear", 3)
    with pytest.raises(ValueError, match="unknown fruit 'plum'; choose one of pear, apple"):
        r["plum"]
    with pytest.raises(ValueError, match="non-empty name"):
        r.register("", 4)


def test_a_temporary_entry_is_gone_after_its_block_also_when_it_fails():
    r = Registry("fruit", ConfigError)
    r.register("pear", 1)
    with pytest.raises(RuntimeError), r.temporarily("plum", 5):
        assert r.names() == ("pear", "plum") and r["plum"] == 5
        raise RuntimeError("the block fails")
    assert r.names() == ("pear",)
    with pytest.raises(ConfigError, match="unknown fruit 'plum'"):
        r["plum"]


FRUITS = Registry("fruit")
FRUITS.register("pear", None)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Basket(Settings):
    section = "basket"
    fruit: Annotated[str, FRUITS] = setting("pear", "the fruit")


def test_a_setting_typed_by_a_registry_takes_its_names_when_checked():
    with pytest.raises(ConfigError, match="basket.fruit must be one of pear, got 'plum'"):
        Basket(fruit="plum")
    with FRUITS.temporarily("plum", None):
        assert Basket(fruit="plum").fruit == "plum"
    with pytest.raises(ConfigError, match="must be one of pear"):
        Basket(fruit="plum")
