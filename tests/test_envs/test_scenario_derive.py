"""``Scenario.derive``: a variant of a built scenario from its typed options, the same as the
scenario its label with the new options names (the rule every other way in follows)."""

from __future__ import annotations

import pytest

from envs.scenarios import make_scenario
from infra.errors import ConfigError

LABELS = ["catchup-v1", "ring-v1", "slowdown-v1:humans=2+5", "sine-v1:amplitude_mps=2.0",
          "catchup-v1:classes=bus+van+car*6", "ring-v1:cav_fraction=1.0"]
DRAWS = [{}, {"cav_fraction": 0.37, "placement": "random", "placement_seed": 5},
         {"class_mix": "bus*2+car*6", "class_seed": 3}]


@pytest.mark.parametrize("label", LABELS)
@pytest.mark.parametrize("draw", DRAWS, ids=["none", "seats", "classes"])
def test_derive_equals_the_label_with_the_options(label: str, draw: dict) -> None:
    built = make_scenario(label)
    try:
        expected = make_scenario(built.label, **draw)
    except ConfigError as err:  # the same refusal, word for word
        with pytest.raises(ConfigError) as got:
            built.derive(**draw)
        assert str(got.value) == str(err)
        return
    derived = built.derive(**draw)
    assert derived == expected and derived.label == expected.label
    assert derived.arrangement(8) == expected.arrangement(8)


def test_given_holds_the_labels_options_typed() -> None:
    sc = make_scenario("sine-v1:amplitude_mps=2,frequency_hz=0.1")
    assert sc.given == {"amplitude_mps": 2.0, "frequency_hz": 0.1}
    assert make_scenario("catchup-v1").given == {}
    # an option at its default is not in the label, so not given
    default = make_scenario("sine-v1").options["amplitude_mps"]
    assert make_scenario("sine-v1", amplitude_mps=default).given == {}
