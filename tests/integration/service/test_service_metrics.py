"""``GET /metrics`` on the simulated cell after a run, and the Grafana dashboard in the repository against a live
scrape: every metric its PromQL queries exists."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import httpx
import pytest
from conftest import WAIT_S, Arms, serving, sim_config
from test_service_http import CAMERA, CELL, FAST, wait_for

pytest.importorskip("prometheus_client")

from prometheus_client.parser import text_string_to_metric_families

from cellcal.core.service import Service
from cellcal.core.service.calibration import Z95

DASHBOARD = Path(__file__).resolve().parents[3] / "docs" / "service" / "grafana-dashboard.json"
TOKEN = "metrics-test-token-0123456789"
#: PromQL words that are not metric names (functions are told by the "(" after them).
_KEYWORDS = {"by", "without", "on", "ignoring", "group_left", "group_right", "bool", "and", "or", "unless",
             "offset", "inf", "nan"}


def metric_names(expr: str) -> set[str]:
    """The metric names a PromQL expression selects."""
    text = re.sub(r'"(?:[^"\\]|\\.)*"', '""', expr)  # string literals
    text = re.sub(r"\{[^}]*\}", "", text)  # label matchers
    text = re.sub(r"\[[^\]]*\]", "", text)  # range selectors ([1h], [$__range])
    text = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", "", text)  # grouping labels
    names = set()
    for match in re.finditer(r"[A-Za-z_:][A-Za-z0-9_:]*", text):
        word, after = match.group(0), text[match.end():].lstrip()[:1]
        preceding = text[:match.start()].rstrip()[-1:]
        if after == "(" or word.lower() in _KEYWORDS or preceding == "$" or re.fullmatch(r"[eE]\d*", word):
            continue  # a function, a keyword, a Grafana variable
        names.add(word)
    return names


def dashboard_queries() -> list[str]:
    document = json.loads(DASHBOARD.read_text(encoding="utf-8"))
    queries = [t["expr"] for panel in document["panels"] for t in panel.get("targets", [])]
    for variable in document["templating"]["list"]:
        query = variable.get("query")
        if isinstance(query, dict):
            queries.append(re.sub(r"^label_values\((\w+),.*\)$", r"\1", query["query"]))
    return queries


def test_the_query_parser_finds_the_metrics_and_nothing_else() -> None:
    expr = ('histogram_quantile(0.95, sum by (le, kind) (rate(cellcal_run_duration_seconds_bucket'
            '{cell=~"$cell", kind!="x"}[1h]))) / on (cell) group_left cellcal_service_info * 1e3')
    assert metric_names(expr) == {"cellcal_run_duration_seconds_bucket", "cellcal_service_info"}


def test_metrics_after_a_run_and_every_dashboard_metric_in_a_live_scrape(tmp_path: Path, arms: Arms) -> None:
    service = Service([sim_config(tmp_path)], tmp_path / "out", build=arms)
    with serving(service, token=TOKEN) as base, httpx.Client(base_url=base, timeout=WAIT_S) as client:
        started = client.post(f"{CELL}/runs", json=FAST, headers={"Authorization": f"Bearer {TOKEN}"})
        assert wait_for(client, started.json()["id"])["state"] == "ok"
        service.bus.publish("drift.mount", {"cell": "paper-sim", "camera": "camera", "rotation_deg": 0.4})
        plane = client.get(f"{CAMERA}/calibration").json()["plane_base"]
        scraped = httpx.get(base.removesuffix("/v1") + "/metrics")  # no token needed to read
    assert scraped.status_code == 200 and scraped.headers["content-type"].startswith("text/plain")
    samples = {(s.name, tuple(sorted(s.labels.items()))): s.value
               for family in text_string_to_metric_families(scraped.text) for s in family.samples}
    cam = (("camera", "camera"), ("cell", "paper-sim"))
    assert samples[("cellcal_runs_total", (("cell", "paper-sim"), ("kind", "calibrate"), ("status", "ok")))] == 1
    assert samples[("cellcal_run_duration_seconds_count",
                    (("cell", "paper-sim"), ("kind", "calibrate"), ("status", "ok")))] == 1
    assert samples[("cellcal_frames_fitted_total", cam)] == 3  # the sim's 3 poses, one frame each, every gate passed
    assert samples[("cellcal_drift_events_total", (*cam, ("kind", "mount")))] == 1
    assert samples[("cellcal_runs_active", (("cell", "paper-sim"),))] == 0
    # the plane's figures: the sim's reference normal is base +z
    normal = plane["normal"]
    assert samples[("cellcal_plane_tilt_rad", cam)] == pytest.approx(math.acos(abs(normal[2])), abs=1e-12)
    assert samples[("cellcal_plane_height_halfwidth_m", cam)] == pytest.approx(plane["height_halfwidth_m"], rel=1e-12)
    assert samples[("cellcal_plane_tilt_halfwidth_rad", cam)] == pytest.approx(Z95 * max(plane["tilt_sigma_rad"]),
                                                                               rel=1e-12)
    assert samples[("cellcal_plane_height_m", cam)] == pytest.approx(-plane["offset_m"] * math.copysign(1, normal[2]),
                                                                     abs=1e-15)
    # every metric the dashboard queries is in the scrape
    names = {name for name, _ in samples}
    queried = set()
    for expr in dashboard_queries():
        found = metric_names(expr)
        assert found, f"no metric in {expr!r}"
        queried |= found
    assert queried - names == set(), f"the dashboard queries metrics the service does not export: {queried - names}"
    assert {"cellcal_plane_tilt_rad", "cellcal_plane_height_m", "cellcal_drift_events_total",
            "cellcal_frames_refused_total", "cellcal_run_duration_seconds_bucket", "cellcal_runs_total"} <= queried
