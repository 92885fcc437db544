"""The spec's one-field ranges (engine.setup.spec.FIELD_RANGES): the validator enforces exactly the table that
the JSON schema publishes, ends open or closed as stated."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from engine.setup.spec import FIELD_RANGES, SPECIES_RANGES, SimulationSpec, Species


def _field_errors(model, data: dict, field: str) -> list[str]:
    try:
        model.model_validate(data)
    except ValidationError as exc:
        return [e["msg"] for e in exc.errors() if e["loc"] == (field,)]
    return []


def _probes(r):
    """(value, inside?) at and around both ends of a range."""
    step = 1 if r.integer else 1e-9 * max(1.0, abs(r.low))
    out = [(r.low, not r.low_open), (r.low - step, False)]
    if r.high != math.inf:
        hstep = 1 if r.integer else 1e-9 * max(1.0, abs(r.high))
        out += [(r.high, not r.high_open), (r.high + hstep, False)]
    else:
        out += [(math.inf, False)]
    return out


@pytest.mark.parametrize("model, ranges", [(SimulationSpec, FIELD_RANGES), (Species, SPECIES_RANGES)])
def test_validator_follows_the_range_table(model, ranges):
    base = {} if model is SimulationSpec else {"radius_ratio": 1.0, "number_fraction": 1.0}
    for field, r in ranges.items():
        for value, inside in _probes(r):
            errors = _field_errors(model, {**base, field: value}, field)
            assert (not errors) == inside, (field, value, errors)
            if errors:
                assert f"{field} = {value}" in errors[0]   # names the field and the value
        assert not _field_errors(model, {**base, field: float("nan")}, field) == [], field


def test_schema_carries_the_table():
    props = SimulationSpec.model_json_schema()["properties"]
    for field, r in FIELD_RANGES.items():
        branch = next(b for b in props[field].get("anyOf", [props[field]]) if b.get("type") != "null")
        assert {k: branch[k] for k in r.json_schema()} == r.json_schema(), field
    assert props["species"]["anyOf"][0]["maxItems"] == 16


def test_every_field_states_its_values_in_the_schema():
    """A number carries a range, a string an enum, the species list its length (a boolean has its two values);
    a new field without one fails here."""
    props = SimulationSpec.model_json_schema()["properties"]
    for field, prop in props.items():
        branch = next(b for b in prop.get("anyOf", [prop]) if b.get("type") != "null")
        if branch.get("type") in ("number", "integer"):
            assert field in FIELD_RANGES and ("minimum" in branch or "exclusiveMinimum" in branch), field
        elif branch.get("type") == "string":
            assert branch.get("enum"), field
        elif branch.get("type") == "boolean":
            assert field == "orientations", field
        else:
            assert field == "species" and branch["type"] == "array" and branch["minItems"] == 1, field
