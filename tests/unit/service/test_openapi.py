"""The committed OpenAPI schema of the HTTP face is the one the code serves.

When the API changes on purpose, rewrite the copy with
``cellcal serve --print-openapi > docs/service/openapi-v1.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("fastapi")

from cellcal.core.service.http import openapi_document

COPY = Path(__file__).resolve().parents[3] / "docs" / "service" / "openapi-v1.json"


def test_the_committed_schema_is_the_served_one() -> None:
    served = json.loads(json.dumps(openapi_document()))  # as JSON has it (tuples as lists)
    committed = json.loads(COPY.read_text(encoding="utf-8"))
    assert served == committed, ("docs/service/openapi-v1.json is out of date: "
                                 "cellcal serve --print-openapi > docs/service/openapi-v1.json")


def test_the_schema_is_versioned_and_documents_errors_and_the_token() -> None:
    document = openapi_document()
    assert document["info"]["version"] == "1"
    assert all(path.startswith("/v1/") for path in document["paths"])
    start = document["paths"]["/v1/cells/{cell}/runs"]["post"]
    assert {"401", "409", "413", "422", "429"} <= set(start["responses"])
    assert start["security"] == [{"HTTPBearer": []}]
    assert "requestBody" in document["paths"]["/v1/cells/{cell}/cameras/{camera}/pixel_to_base"]["post"]
