"""The OpenAPI document itself: bearer auth declared exactly when a token is set, the spec's one-field limits,
the renderer choices of this server, the batch's one-of. (Fuzzing every operation against the document:
test_schemathesis.py, with the ``fuzz`` extra.)"""

from __future__ import annotations

import pytest

from service.app import create_app
from tests.jobs.conftest import make_settings

TOKEN = "openapi-token"


def _security(document: dict) -> dict[str, object]:
    return {f"{method.upper()} {path}": op.get("security")
            for path, ops in document["paths"].items() for method, op in ops.items()}


def test_bearer_auth_declared_exactly_when_a_token_is_set(tmp_path):
    open_doc = create_app(make_settings(tmp_path / "a")).openapi()
    assert "securitySchemes" not in open_doc.get("components", {})
    assert set(_security(open_doc).values()) == {None}
    token_doc = create_app(make_settings(tmp_path / "b", token=TOKEN)).openapi()
    assert token_doc["components"]["securitySchemes"]["HTTPBearer"] == {
        "type": "http", "scheme": "bearer",
        "description": "The server's token (DEMQ_TOKEN); declared only when one is set."}
    declared = _security(token_doc)
    assert declared.pop("GET /healthz") is None            # the health check stays open
    assert declared and all(sec == [{"HTTPBearer": []}] for sec in declared.values()), declared


def test_spec_ranges_are_in_the_schema(tmp_path):
    """The spec's one-field limits appear in the document as the validator enforces them (spot checks)."""
    props = create_app(make_settings(tmp_path)).openapi()["components"]["schemas"]["SimulationSpecIn"]["properties"]
    assert props["e_n"]["exclusiveMinimum"] == 0 and props["e_n"]["maximum"] == 1
    assert props["volume_fraction"]["exclusiveMaximum"] == 0.64
    assert props["seed"]["maximum"] == 2**63 - 1 and isinstance(props["seed"]["maximum"], int)
    assert props["backend"]["enum"] == ["auto", "cpu", "cuda"]
    assert props["precision"]["enum"] == ["float64", "float32", "mixed"]
    assert {"minimum": 0} .items() <= props["friction"]["anyOf"][0].items()


@pytest.mark.parametrize("ovito", [False, True])
def test_renderer_enum_is_what_the_server_runs(tmp_path, monkeypatch, ovito):
    """The snapshot's renderer choices are those of the server, decided when the app is created: 'ovito' only where
    OVITO can render."""
    from service import render

    monkeypatch.setattr(render, "ovito_available", lambda: ovito)
    operation = create_app(make_settings(tmp_path)).openapi()["paths"]["/jobs/{job_id}/snapshot.png"]["get"]
    (renderer,) = [p["schema"] for p in operation["parameters"] if p["name"] == "renderer"]
    assert renderer["enum"] == (["auto", "ovito", "matplotlib"] if ovito else ["auto", "matplotlib"])
    assert renderer["default"] == "auto"


def test_empty_batch_is_invalid_by_the_schema_too(tmp_path):
    batch = create_app(make_settings(tmp_path)).openapi()["components"]["schemas"]["BatchIn"]
    assert batch["oneOf"] == [{"required": ["specs"]}, {"required": ["sweep"]}]
