"""The history store's writes and queries, the same test functions on SQLite and on a real PostgreSQL server."""

from __future__ import annotations

import json
import math
import sys
import threading
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest
from ports import free_port
from postgres import database_url, postgres_server  # noqa: F401  (pytest fixtures)

from cellcal.core.service.history import MAX_PAGE, HistoryStore, NewCalibration
from cellcal.devices.errors import ConfigError, MissingDependencyError, OutputError

T0 = datetime(2024, 5, 1, 10, 0, 0, tzinfo=UTC)


def at(seconds: float = 0.0, us: int = 0) -> datetime:
    """T0 plus whole seconds and microseconds (exact: no float microseconds)."""
    return T0 + timedelta(seconds=seconds, microseconds=us)


@pytest.fixture
def store(database_url: str) -> Iterator[HistoryStore]:  # noqa: F811
    s = HistoryStore(database_url)
    yield s
    s.close()


def test_covariance_and_pose_floats_read_back_bit_for_bit(store: HistoryStore) -> None:
    # floats whose shortest repr is long, the extremes of float64, a subnormal and a negative zero
    special = [1 / 3, 0.1 + 0.2, math.pi * 1e-9, 2.2250738585072014e-308, 5e-324, 1.7976931348623157e308,
               -0.0, 1e-7 / 3, 123456.789e-12]
    rng = np.random.default_rng(41)
    a = rng.normal(scale=1e-3, size=(6, 6))
    cov = a @ a.T  # a symmetric positive definite 6x6, m^2 / rad^2 / m*rad
    cov[0, :len(special[:6])] = special[:6]
    pose = {"translation_m": [0.1 + 0.2, -0.0, 1 / 3], "rotvec_rad": [math.pi / 7, 2e-17, -1e-300]}
    aid = store.record_applied("wrist", "mount", pose, covariance=cov, applied_at=at())
    rec = store.calibration_at("wrist", "mount", at())
    assert rec is not None and rec.id == aid
    back = np.array(rec.covariance, dtype=np.float64)
    assert back.shape == (6, 6)
    assert [float(x).hex() for x in back.ravel()] == [float(x).hex() for x in cov.ravel()]  # bit for bit
    got = rec.value["translation_m"] + rec.value["rotvec_rad"]
    want = pose["translation_m"] + pose["rotvec_rad"]
    assert [float(x).hex() for x in got] == [float(x).hex() for x in want]
    assert math.copysign(1.0, rec.value["translation_m"][1]) == -1.0  # the sign of -0.0 kept
    eid = store.record_event("wrist", "drift", detail={"values": special}, at=at())
    (event,) = store.events(at(), at(1)).items
    assert event.id == eid and [x.hex() for x in event.detail["values"]] == [x.hex() for x in special]


def test_events_order_to_the_microsecond_within_one_second(store: HistoryStore) -> None:
    # written out of order, all inside 10:00:00; two share one microsecond exactly
    written = [("late", at(0, 900_000)), ("first", at(0, 1)), ("tie-a", at(0, 500_000)), ("tie-b", at(0, 500_000)),
               ("before", at(-1, 999_999)), ("next-second", at(1)), ("zero", at(0))]
    for kind, t in written:
        store.record_event("wrist", kind, at=t)
    page = store.events(at(0), at(1))  # [10:00:00, 10:00:01): the end excluded
    assert [e.kind for e in page.items] == ["zero", "first", "tie-a", "tie-b", "late"]
    assert [e.at for e in page.items] == ["2024-05-01T10:00:00.000000Z", "2024-05-01T10:00:00.000001Z",
                                          "2024-05-01T10:00:00.500000Z", "2024-05-01T10:00:00.500000Z",
                                          "2024-05-01T10:00:00.900000Z"]
    assert page.next_cursor is None
    # an ISO string with another offset is the same instant: 12:00:00.5+02:00 == 10:00:00.5Z
    assert [e.kind for e in store.events("2024-05-01T12:00:00.5+02:00", "2024-05-01T10:00:00.500001Z").items] \
        == ["tie-a", "tie-b"]
    assert [e.kind for e in store.events(at(0), at(1), camera="other").items] == []
    assert [e.kind for e in store.events(kind="before").items] == ["before"]


def test_calibration_at_time_before_at_and_after_each_application(store: HistoryStore) -> None:
    store.record_applied("wrist", "mount", {"t_m": [0.0, 0.0, 0.10]}, applied_at=at(100))
    store.record_applied("wrist", "mount", {"t_m": [0.0, 0.0, 0.11]}, applied_at=at(200))
    store.record_applied("wrist", "plane", {"n": [0, 0, 1], "d_m": 0.5}, applied_at=at(150))
    store.record_applied("other", "mount", {"t_m": [9.0, 9.0, 9.0]}, applied_at=at(50))

    def mount_z(t: datetime) -> float | None:
        rec = store.calibration_at("wrist", "mount", t)
        return None if rec is None else rec.value["t_m"][2]

    assert mount_z(at(100, -1)) is None  # one microsecond before the first application
    assert mount_z(at(100)) == 0.10  # at it: the one applied then
    assert mount_z(at(199, 999_999)) == 0.10
    assert mount_z(at(200)) == 0.11
    assert mount_z(at(10_000)) == 0.11
    assert store.calibration_at("wrist", "mount", "2024-05-01T10:01:40Z").value["t_m"][2] == 0.10  # = at(100)
    state = store.state_at("wrist", at(160))
    assert sorted(state) == ["mount", "plane"] and state["mount"].value["t_m"][2] == 0.10
    assert store.state_at("wrist", at(99)) == {}
    # two applied in one microsecond: the later write is the one in use
    store.record_applied("wrist", "camera_base", {"k": 1}, applied_at=at(300))
    store.record_applied("wrist", "camera_base", {"k": 2}, applied_at=at(300))
    assert store.calibration_at("wrist", "camera_base", at(300)).value == {"k": 2}
    assert [r.value["t_m"][2] for r in store.list_applied(camera="wrist", what="mount").items] == [0.11, 0.10]


def test_run_pages_are_newest_first_bounded_and_complete(store: HistoryStore) -> None:
    ids = []
    for i in range(120):  # two runs start in each second: ties are broken by id
        kind = "calibrate" if i % 3 else "handeye"
        ids.append(store.start_run(kind, f"cam{i % 2}", "configs/sim.toml", started=at(i // 2)))
    pages, cursor = [], None
    while True:
        page = store.list_runs(limit=50, cursor=cursor)
        pages.append(page.items)
        cursor = page.next_cursor
        if cursor is None:
            break
    assert [len(p) for p in pages] == [50, 50, 20]
    seen = [r.id for p in pages for r in p]
    assert seen == sorted(ids, reverse=True)  # newest start first, the later id first within a second
    starts = [r.started for p in pages for r in p]
    assert starts == sorted(starts, reverse=True)
    assert [r.id for r in store.list_runs(camera="cam1", kind="handeye", limit=MAX_PAGE).items] == \
        [i for i in sorted(ids, reverse=True) if (i - ids[0]) % 2 == 1 and (i - ids[0]) % 3 == 0]
    assert len(store.list_runs(limit=MAX_PAGE).items) == 120
    for bad in (0, MAX_PAGE + 1, -5):
        with pytest.raises(ConfigError, match="page size"):
            store.list_runs(limit=bad)
    with pytest.raises(ConfigError, match="not a cursor"):
        store.list_runs(cursor="yesterday")


def test_a_run_from_start_to_finish_with_what_it_applied(store: HistoryStore) -> None:
    rid = store.start_run("calibrate", "wrist", "configs/sim.toml", started=at(0))
    assert store.run(rid).status == "running" and store.run(rid).ended is None
    cal = NewCalibration("wrist", "mount", {"t_m": [0.01, 0.02, 0.1]}, covariance=np.eye(6) * 1e-8)
    done = store.finish_run(rid, "ok", result={"rms_px": 0.21, "n": 12}, ended=at(42), applied=[cal])
    assert (done.status, done.started, done.ended, done.result) == \
        ("ok", "2024-05-01T10:00:00.000000Z", "2024-05-01T10:00:42.000000Z", {"rms_px": 0.21, "n": 12})
    applied = store.calibration_at("wrist", "mount", at(42))
    assert applied.run_id == rid and applied.applied == done.ended and applied.covariance[5][5] == 1e-8
    with pytest.raises(ConfigError, match=f"run {rid} has ended already"):
        store.finish_run(rid, "failed")
    with pytest.raises(ConfigError, match="run 999999 is not in the history"):
        store.finish_run(999999, "ok")
    assert store.run(999999) is None
    stale = store.start_run("depthcal", "", started=at(50))
    assert store.abandon_running("the service stopped during the run", ended=at(60)) == 1
    rec = store.run(stale)
    assert (rec.status, rec.reason, rec.camera) == ("failed", "the service stopped during the run", "")
    assert store.run(rid).status == "ok"  # the finished run untouched


def test_an_oversized_document_is_refused_and_nothing_changes(database_url: str) -> None:  # noqa: F811
    with HistoryStore(database_url, max_document_bytes=1000) as store:
        rid = store.start_run("handeye", "wrist", started=at(0))
        store.record_event("wrist", "knock", detail={"pad": "x" * 500}, at=at(1))  # 510 bytes of JSON: kept
        with pytest.raises(OutputError) as err:
            store.finish_run(rid, "ok", result={"pad": "x" * 2000})  # 2010 bytes of JSON
        assert str(err.value).count("\n") == 0 and "2010 bytes" in str(err.value) and "1000" in str(err.value)
        with pytest.raises(OutputError, match="over the limit"):
            store.record_applied("wrist", "mount", {"t": [0.0] * 400})
        assert store.run(rid).status == "running"
        assert store.list_applied().items == ()
        assert [e.detail["pad"] for e in store.events().items] == ["x" * 500]


def test_a_failed_write_rolls_back_and_keeps_earlier_rows(store: HistoryStore, monkeypatch: pytest.MonkeyPatch) -> None:
    first = store.start_run("calibrate", "wrist", started=at(0))
    store.finish_run(first, "ok", result={"k": 1}, ended=at(1),
                     applied=[NewCalibration("wrist", "plane", {"d_m": 0.5})])
    second = store.start_run("calibrate", "wrist", started=at(2))

    def fail(*args: object) -> int:
        raise RuntimeError("disk pulled out after the run's update")

    monkeypatch.setattr(HistoryStore, "_insert_applied", fail)  # fails inside finish_run's transaction
    with pytest.raises(RuntimeError, match="disk pulled"):
        store.finish_run(second, "ok", ended=at(3), applied=[NewCalibration("wrist", "plane", {"d_m": 0.6})])
    monkeypatch.undo()
    assert store.run(second).status == "running"  # the update rolled back with the failed insert
    assert [r.value["d_m"] for r in store.list_applied().items] == [0.5]
    with pytest.raises(ConfigError, match="run 777 is not in the history"):
        store.record_applied("wrist", "mount", {"t": [0, 0, 0]}, run_id=777)
    assert store.run(first).result == {"k": 1} and len(store.list_applied().items) == 1
    store.finish_run(second, "cancelled", reason="operator pressed stop", ended=at(4))  # still writable
    assert store.run(second).reason == "operator pressed stop"


def test_eight_threads_writing_at_once_leave_every_row(store: HistoryStore) -> None:
    threads_n, per_thread = 8, 40
    barrier = threading.Barrier(threads_n)
    errors: list[BaseException] = []

    def worker(k: int) -> None:
        try:
            barrier.wait()
            for i in range(per_thread):
                store.record_event(f"cam{k}", "track", detail={"i": i}, at=at(i))
                if i % 10 == 0:
                    rid = store.start_run("calibrate", f"cam{k}", started=at(i))
                    store.finish_run(rid, "ok", result={"k": k, "i": i}, ended=at(i, 1),
                                     applied=[NewCalibration(f"cam{k}", "mount", {"i": i})])
        except BaseException as exc:  # reported below: a thread's exception is otherwise lost
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(threads_n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    everything, cursor = [], None
    while True:
        page = store.events(limit=100, cursor=cursor)
        everything += page.items
        if (cursor := page.next_cursor) is None:
            break
    assert len(everything) == threads_n * per_thread and len({e.id for e in everything}) == threads_n * per_thread
    for k in range(threads_n):  # each camera's events all there, in its own order
        assert [e.detail["i"] for e in everything if e.camera == f"cam{k}"] == list(range(per_thread))
    runs = store.list_runs(limit=MAX_PAGE).items
    assert len(runs) == threads_n * per_thread // 10 and {r.status for r in runs} == {"ok"}
    assert len(store.list_applied(limit=MAX_PAGE).items) == threads_n * per_thread // 10
    for k in range(threads_n):
        assert store.calibration_at(f"cam{k}", "mount", at(100)).value == {"i": 30}


def test_reopening_finds_every_row(database_url: str) -> None:  # noqa: F811
    with HistoryStore(database_url) as store:
        rid = store.start_run("fixed-handeye", "ceiling", "cell-a.toml", started=at(0))
        store.record_event("ceiling", "knock", at=at(5))
    with HistoryStore(database_url) as again:
        assert again.migrated_from == again.schema_version == 2
        assert again.run(rid).source == "cell-a.toml" and [e.kind for e in again.events().items] == ["knock"]


def test_bad_arguments_are_one_line_config_errors(store: HistoryStore) -> None:
    cases = [
        (lambda: store.start_run("calibrat", "wrist"), "not one of calibrate, handeye"),
        (lambda: store.record_event("wrist", "knock", at=datetime(2024, 5, 1, 10)), "has no timezone"),
        (lambda: store.record_event("wrist", "knock", at="2024-05-01 10:00"), "has no timezone"),
        (lambda: store.record_event("wrist", "knock", at="last tuesday"), "not an ISO 8601 time"),
        (lambda: store.record_applied("wrist", "tool", {"t": 1}), "not one of mount, plane, camera_base"),
        (lambda: store.record_applied("", "mount", {"t": 1}), "non-empty name"),
        (lambda: store.calibration_at("wrist", "mount", "soon"), "not an ISO 8601 time"),
        (lambda: store.finish_run(1, "running"), "not one of ok, failed, cancelled"),
    ]
    for call, words in cases:
        with pytest.raises(ConfigError, match=words) as err:
            call()
        assert "\n" not in str(err.value)


def test_urls_that_name_no_usable_database(tmp_path: object) -> None:
    for url, words in [("mysql://u@h/db", "neither sqlite:///PATH nor postgresql://"),
                       (f"sqlite:///{tmp_path}/no/such/dir/h.sqlite", "cannot open"),
                       ("sqlite:///", "names no file")]:
        with pytest.raises(ConfigError, match=words) as err:
            HistoryStore(url)
        assert "\n" not in str(err.value)
    pytest.importorskip("psycopg")
    with pytest.raises(ConfigError, match="cannot connect") as err:
        HistoryStore(f"postgresql://cellcal:secret@127.0.0.1:{free_port()}/db", busy_timeout_s=2)
    assert "\n" not in str(err.value) and "secret" not in str(err.value) and ":***@" in str(err.value)


def test_postgres_without_psycopg_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "psycopg", None)  # import psycopg now raises ImportError
    with pytest.raises(MissingDependencyError, match=r"pip install 'cellcal\[postgres\]'") as err:
        HistoryStore("postgresql://cellcal@127.0.0.1:5432/history")
    assert "\n" not in str(err.value)


def test_records_are_json_data(store: HistoryStore) -> None:
    rid = store.start_run("calibrate", "wrist", started=at(0))
    store.finish_run(rid, "failed", reason="quality gate 'rms' failed", ended=at(1), result={"nan": float("nan")})
    doc = json.loads(json.dumps(store.run(rid).as_dict(), allow_nan=False))
    assert doc["result"] == {"nan": None} and doc["reason"] == "quality gate 'rms' failed"


def test_times_not_given_are_the_clocks(database_url: str) -> None:  # noqa: F811
    now = datetime(2031, 2, 3, 4, 5, 6, 789012, tzinfo=UTC)
    with HistoryStore(database_url, clock=lambda: now) as store:
        rid = store.start_run("calibrate", "wrist")
        store.record_event("wrist", "knock")
        store.finish_run(rid, "ok", applied=[NewCalibration("wrist", "plane", {"d_m": 0.5})])
        assert store.run(rid).started == store.run(rid).ended == "2031-02-03T04:05:06.789012Z"
        assert store.events().items[0].at == store.calibration_at("wrist", "plane", now).applied == store.run(rid).ended
