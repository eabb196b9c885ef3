"""Bad requests to the HTTP face: each a 4xx with the body {"error": "<one line>"}, no traceback, nothing moved.

FastAPI's TestClient is enough here (no socket adds anything to a refusal); the real socket is in
test_service_http.py and the command in test_serve_cli.py.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import Arms, sim_config
from fastapi.testclient import TestClient

from cellcal.core.service import Service
from cellcal.core.service.http import create_app

TOKEN = "a-test-token-0123456789"
RUNS = "/v1/cells/paper-sim/runs"
PIXELS = "/v1/cells/paper-sim/cameras/camera/pixel_to_base"
FLANGE = {"translation_m": [0.3, 0.0, 0.5], "quaternion_xyzw": [1.0, 0.0, 0.0, 0.0]}


@pytest.fixture
def client(tmp_path: Path, arms: Arms) -> Iterator[TestClient]:
    service = Service([sim_config(tmp_path)], tmp_path / "out", build=arms)
    with TestClient(create_app(service, token=TOKEN, max_body_bytes=4096, rate_per_s=1000.0)) as test_client:
        yield test_client


def refused(response: Any, status: int, *words: str) -> str:
    """The response is ``status`` with exactly ``{"error": one line}`` holding ``words``; its line."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/json")
    body = response.json()
    assert list(body) == ["error"] and isinstance(body["error"], str)
    line: str = body["error"]
    assert "\n" not in line and "Traceback" not in line and 0 < len(line) <= 500
    for word in words:
        assert word in line
    return line


def test_state_changes_need_the_token(client: TestClient, arms: Arms) -> None:
    run = {"kind": "calibrate", "camera": "camera", "options": {"report": False}}
    refused(client.post(RUNS, json=run), 401, "Authorization: Bearer")
    refused(client.post(RUNS, json=run, headers={"Authorization": "Bearer wrong-token-0123456789"}), 401, "wrong")
    refused(client.post(RUNS, json=run, headers={"Authorization": f"Basic {TOKEN}"}), 401, "Bearer")
    refused(client.post("/v1/runs/nope/cancel"), 401)
    assert arms.built == []  # no device was even built
    assert client.get("/v1/health").status_code == 200  # reading needs no token
    assert client.post(PIXELS, json={"pixels": [1, 2], "flange_pose": FLANGE}).status_code == 404  # nor mapping


def test_malformed_json_wrong_types_and_unknown_names(client: TestClient, arms: Arms) -> None:
    auth = {"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"}
    refused(client.post(RUNS, content=b'{"kind": "calibrate",', headers=auth), 400, "malformed JSON")
    refused(client.post(PIXELS, content=b"[1, 2", headers=auth), 400, "malformed JSON")
    refused(client.post(RUNS, json={"kind": "calibrate", "camera": 7}, headers=auth), 422, "camera")
    refused(client.post(RUNS, json={"kind": "paint", "camera": "camera"}, headers=auth), 422, "kind")
    refused(client.post(RUNS, json={"kind": "calibrate", "camera": "camera", "options": {"report": "yes"}},
                        headers=auth), 422, "report")
    refused(client.post(RUNS, json={"kind": "calibrate", "camera": "camera", "extra": 1}, headers=auth), 422)
    refused(client.post(RUNS, json={"kind": "calibrate", "camera": "nope"}, headers=auth), 404, "no camera 'nope'")
    refused(client.post("/v1/cells/nope/runs", json={"kind": "calibrate", "camera": "camera"}, headers=auth), 404)
    refused(client.post(PIXELS, json={"pixels": ["a", 1], "flange_pose": FLANGE}), 422, "pixels")
    refused(client.post(PIXELS, json={"pixels": [1, 2], "flange_pose": {"translation_m": [0, 0]}}), 422,
            "flange_pose")
    refused(client.post(PIXELS, json={"pixels": [1, 2], "flange_pose": {**FLANGE, "quaternion_xyzw": [1, 1, 0, 0]}}),
            422, "unit quaternion")
    refused(client.post(PIXELS, json={"pixels": [1, 2]}), 422, "flange_pose")
    refused(client.get("/v1/runs/nope"), 404, "no run")
    refused(client.get("/v1/nothing-here"), 404)
    refused(client.delete(RUNS), 405)
    assert arms.built == []


def test_a_body_over_the_bound_is_413_by_its_length_or_as_it_streams(client: TestClient) -> None:
    big = b'{"pixels": [' + b"[1.0, 2.0], " * 1000 + b'[1.0, 2.0]], "flange_pose": {}}'
    refused(client.post(PIXELS, content=big, headers={"Content-Type": "application/json"}), 413, "4096 bytes")

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as it comes
        for i in range(0, len(big), 1000):
            yield big[i:i + 1000]

    refused(client.post(PIXELS, content=chunks(), headers={"Content-Type": "application/json"}), 413)
    assert client.get("/v1/health").status_code == 200  # still serving


def test_too_many_requests_is_429_with_retry_after(tmp_path: Path) -> None:
    service = Service([sim_config(tmp_path)], tmp_path / "out")
    with TestClient(create_app(service, rate_per_s=0.5, burst=3)) as client:
        assert [client.get("/v1/health").status_code for _ in range(3)] == [200, 200, 200]
        response = client.get("/v1/health")
        refused(response, 429, "too many requests")
        assert int(response.headers["retry-after"]) >= 1
