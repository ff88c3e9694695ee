"""Scenarios: names, loading, errors, and the YAML round trip."""

from __future__ import annotations

from collections import Counter

import pytest

from fixtures.scenario import (
    ObjectClass,
    Scenario,
    ScenarioError,
    load_scenario,
    scenario_names,
)


def test_builtin_names_are_listed() -> None:
    assert {"default", "village", "open", "parking"} <= set(scenario_names())


def test_unknown_name_error_lists_the_valid_names() -> None:
    with pytest.raises(ScenarioError) as err:
        load_scenario("no-such-world")
    message = str(err.value)
    assert "no-such-world" in message
    for name in scenario_names():
        assert name in message


@pytest.mark.parametrize("name", ["default", "village", "open", "parking"])
def test_yaml_round_trip(name: str) -> None:
    scenario = load_scenario(name)
    again = Scenario.from_yaml(scenario.to_yaml())
    assert again == scenario
    assert again.to_yaml() == scenario.to_yaml()


def test_load_from_a_yaml_path(tmp_path) -> None:
    scenario = load_scenario("open").with_seed(99)
    path = tmp_path / "mine.yaml"
    path.write_text(scenario.to_yaml())
    assert load_scenario(path) == scenario
    assert load_scenario(str(path)).seed == 99


def test_unknown_field_and_bad_value_are_named() -> None:
    with pytest.raises(ScenarioError, match="wheels"):
        Scenario.from_yaml("terrain: {wheels: 4}")
    with pytest.raises(ScenarioError, match="spaceship"):
        Scenario.from_yaml("agents: [{cls: spaceship}]")
    with pytest.raises(ScenarioError, match="duration_s"):
        Scenario.from_yaml("duration_s: soon")


def test_missing_file_is_named(tmp_path) -> None:
    with pytest.raises(ScenarioError, match=r"nothing\.yaml"):
        load_scenario(tmp_path / "nothing.yaml")


def test_default_scenario_has_what_the_demo_needs() -> None:
    sc = load_scenario("default")
    static_counts = Counter(p.cls for p in sc.populations for _ in range(p.count))
    assert 45 <= sum(static_counts.values()) <= 60
    assert {
        ObjectClass.BUILDING,
        ObjectClass.TREE,
        ObjectClass.BUSH,
        ObjectClass.ROCK,
        ObjectClass.POST,
        ObjectClass.WALL,
        ObjectClass.PERSON,
        ObjectClass.FURNITURE,
    } <= set(static_counts)
    members = [a.members for a in sc.agents]
    assert 7 <= sum(members) <= 10 and max(members) > 1  # some move together
    assert sc.duration_s == 60.0 and sc.terrain.size_m == 400.0
    assert sc.route.speed_mps - sc.route.speed_amplitude_mps >= 5.0
    assert sc.route.speed_mps + sc.route.speed_amplitude_mps <= 10.0


def test_village_and_open_have_their_features() -> None:
    village = load_scenario("village")
    groups = {(a.cls, a.formation.value): a.members for a in village.agents if a.members > 1}
    assert groups[(ObjectClass.PERSON, "crowd")] >= 5  # a crowd
    assert groups[(ObjectClass.VEHICLE, "column")] >= 3  # a convoy
    open_ = load_scenario("open")
    assert open_.route.speed_mps == 15.0
    assert open_.terrain.ditches and open_.terrain.slope_xy != (0.0, 0.0)
