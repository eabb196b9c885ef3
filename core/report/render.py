"""Writing a run's report into its output directory, and rendering it again from the JSON alone (ADR 0037)."""

from __future__ import annotations

from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cellcal.core.report.html import Picture, render_html
from cellcal.devices import boundedjson
from cellcal.devices.errors import ConfigError, MissingDependencyError

__all__ = ["MAX_REPORT_DATA_BYTES", "NO_MATPLOTLIB", "PLAIN_PICTURES", "REPORT_DATA_FILENAME", "REPORT_HTML_FILENAME",
           "REPORT_SCHEMA", "REPORT_TXT_FILENAME", "draw_report", "load_report_data", "needs_matplotlib",
           "new_report_data", "pictures", "render_to_file", "write_report", "write_report_data"]

REPORT_SCHEMA = "cellcal.report/1"
REPORT_HTML_FILENAME = "report.html"
REPORT_TXT_FILENAME = "report.txt"
REPORT_DATA_FILENAME = "report-data.json"
#: Largest report data file read back, bytes.
MAX_REPORT_DATA_BYTES = 200 << 20
#: The one line said when the pictures cannot be drawn.
NO_MATPLOTLIB = "report without pictures: matplotlib is not installed (pip install 'cellcal[plots]')"


def new_report_data(kind: str, camera: str, config_source: str | None) -> dict[str, Any]:
    """The report data's header (schema, kind, camera, time, version); sections are added by the run."""
    from cellcal.devices.version import cellcal_version

    return {"schema": REPORT_SCHEMA, "kind": kind, "camera": camera, "config_source": config_source,
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"), "cellcal_version": cellcal_version(),
            "status": "ok", "error": None, "summary_text": "", kind: {}}


#: Processes that draw the pictures (at most; one per core).
MAX_DRAW_WORKERS = 2


def _jobs(data: Mapping[str, Any]) -> list[tuple[str, str, str, tuple[Any, ...]]]:
    """The pictures to draw: (file name, caption, function of :mod:`figures`, its arguments)."""
    kind = str(data.get("kind"))
    camera = str(data.get("camera", ""))
    section = data.get(kind) or {}
    out: list[tuple[str, str, str, tuple[Any, ...]]] = []
    if kind == "calibrate":
        poses = section.get("poses") or []
        for pose in poses:
            n = int(pose["index"]) + 1
            what = "FAILED pose" if pose.get("failed") else "pose"
            if pose.get("pictures"):
                out.append((f"pose-{n}-image.png", f"{what} {n}: depth, pixel classes and region, residuals",
                            "pose_image_figure", (pose, camera)))
                out.append((f"pose-{n}-fit.png", f"{what} {n}: side view with the fitted plane; gates",
                            "pose_fit_figure", (pose, camera)))
        if any(p.get("full_frame") for p in poses):
            out.append(("poses.png", "tilt and height per pose with 95 % intervals and the consensus",
                        "poses_figure", (poses, camera)))
        cons = ((section.get("result") or {}).get("summary") or {}).get("plane_consistency")
        if cons and cons.get("normal_deviation_deg"):
            out.append(("consistency.png", "cross-pose consistency in the base frame", "consistency_figure",
                        (cons, camera)))
    elif kind == "handeye":
        doc = section.get("result") or {}
        if doc.get("mount"):
            out.append(("handeye-mount.png", "the mount with its intervals" +
                        (" and OpenCV's methods on the board" if doc.get("charuco") else ""),
                        "handeye_mount_figure", (doc, camera)))
        if doc.get("poses"):
            out.append(("handeye-residuals.png", "per-pose residuals", "handeye_residuals_figure", (doc, camera)))
        if (doc.get("fit") or {}).get("covariance"):
            out.append(("handeye-observability.png", "observability of each parameter",
                        "handeye_observability_figure", (doc, camera)))
        if (doc.get("charuco") or {}).get("views"):
            out.append(("handeye-charuco.png", "ChArUco board poses", "charuco_figure", (doc, camera)))
    elif kind == "handeye-fixed":  # a fixed camera's run (ADR 0061): its own page, handeye-NAME.html
        from cellcal.core.report.fixed_html import fixed_jobs

        out += fixed_jobs(section, camera)
    elif kind == "monitor":
        for label, cam in (section.get("cameras") or {}).items():
            out.append((f"monitor-{_safe(label)}.png", f"camera {label}: tilt and height over time",
                        "monitor_figure", (label, cam.get("series") or {}, cam)))
    return out


def _draw(job: tuple[str, str, str, tuple[Any, ...]]) -> bytes:
    """One job of :func:`_jobs`: the PNG bytes."""
    from cellcal.core.report import figures

    return getattr(figures, job[2])(*job[3])  # type: ignore[no-any-return]


#: The pictures drawn as plain images, without matplotlib (:data:`_jobs`' functions, ADR 0051).
PLAIN_PICTURES = frozenset({"pose_image_figure", "pose_fit_figure", "poses_figure", "consistency_figure",
                            "fixed_pose_figure", "fixed_residuals_figure", "fixed_sigma_figure"})


def needs_matplotlib(data: Mapping[str, Any]) -> bool:
    """Whether a picture of ``data`` is drawn with matplotlib (hand-eye, monitor); the calibrate report's are not.

    Data that cannot be read counts as needing it: the drawing child says what is wrong with it.
    """
    try:
        return any(job[2] not in PLAIN_PICTURES for job in _jobs(data))
    except (KeyError, TypeError, ValueError, IndexError, AttributeError):
        return True


def pictures(data: Mapping[str, Any], workers: int = 1) -> list[Picture]:
    """Every picture of the report, drawn from ``data`` alone (on up to ``workers`` forked processes).

    Raises:
        MissingDependencyError: matplotlib is not installed (extra ``plots``).
    """
    import multiprocessing
    import os

    from cellcal.core.report import canvas, figures

    jobs = _jobs(data)
    # fails early, in one line, without the plots extra; matplotlib imported once, before any fork
    canvas.require()
    if any(job[2] not in PLAIN_PICTURES for job in jobs):
        figures.matplotlib_figure()
    # the slowest first, the map images (the quickest) fill in after them
    order = sorted(range(len(jobs)), key=lambda i: jobs[i][2] == "pose_image_figure")
    workers = min(workers, os.cpu_count() or 1, len(jobs))
    if workers > 1 and "fork" in multiprocessing.get_all_start_methods():
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            drawn = list(pool.map(_draw, [jobs[i] for i in order]))
    else:
        drawn = [_draw(jobs[i]) for i in order]
    pngs = dict(zip(order, drawn, strict=True))
    return [Picture(name, caption, pngs[i]) for i, (name, caption, _, _) in enumerate(jobs)]


def _safe(label: str) -> str:
    """A file-name-safe form of a camera label."""
    return "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in label)[:80] or "camera"


def write_report_data(out_dir: str | Path, data: Mapping[str, Any]) -> Path:
    """Write ``report-data.json`` and ``report.txt`` into ``out_dir`` (numpy and JSON only: no drawing).

    Raises:
        OutputError: A file cannot be written.
    """
    from cellcal.core.calibration.report import write_bytes_atomic, write_json_atomic

    out = Path(out_dir)
    write_bytes_atomic(out / REPORT_TXT_FILENAME, str(data.get("summary_text", "")).encode("utf-8"))
    return write_json_atomic(out / REPORT_DATA_FILENAME, data)


def draw_report(out_dir: str | Path, workers: int = MAX_DRAW_WORKERS) -> tuple[Path, str]:
    """Draw the PNGs and ``report.html`` of ``out_dir`` from its ``report-data.json`` (on up to ``workers``
    forked processes).

    Without matplotlib the page is written without pictures and the note says so in one line.

    Returns:
        The page's path and a note ("" when every picture was drawn).

    Raises:
        ConfigError: The report data is missing or malformed.
        OutputError: A file cannot be written.
    """
    from cellcal.core.calibration.report import write_bytes_atomic

    out = Path(out_dir)
    data = load_report_data(out)
    pics, note = _pictures_or_note(data, out, workers)
    for pic in pics:
        write_bytes_atomic(out / pic.name, pic.png)
    return write_bytes_atomic(out / REPORT_HTML_FILENAME, _page(data, pics, note, out)), note


def write_report(out_dir: str | Path, data: Mapping[str, Any]) -> tuple[Path, str]:
    """:func:`write_report_data` then :func:`draw_report` in this process; the page's path and a note."""
    write_report_data(out_dir, data)
    return draw_report(out_dir)


def _pictures_or_note(data: Mapping[str, Any], directory: Path, workers: int = MAX_DRAW_WORKERS
                      ) -> tuple[list[Picture], str]:
    """The pictures, or none and a one-line note without matplotlib.

    Raises:
        ConfigError: The data is malformed (naming the file).
    """
    try:
        return pictures(data, workers), ""
    except MissingDependencyError:
        return [], NO_MATPLOTLIB
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise ConfigError(f"malformed report data: {type(exc).__name__}: {exc}",
                          source=str(directory / REPORT_DATA_FILENAME)) from None


def load_report_data(directory: str | Path) -> dict[str, Any]:
    """The report data of a run directory (``DIR/report-data.json``), or of a data file named as such
    (``DIR/handeye-NAME.report-data.json``, a fixed camera's).

    Raises:
        ConfigError: No report data there, too large, not JSON, or another schema (exit status 2).
    """
    path = Path(directory)
    if not (path.name.endswith(".json") and not path.is_dir()):
        path = path / REPORT_DATA_FILENAME
    try:
        size = path.stat().st_size
    except OSError:
        raise ConfigError(f"no report data in {directory} (expected {REPORT_DATA_FILENAME}, written by "
                          "calibrate, handeye or monitor --out)", source=str(path)) from None
    if size > MAX_REPORT_DATA_BYTES:
        raise ConfigError(f"{size} bytes, more than the {MAX_REPORT_DATA_BYTES} a report can have", source=str(path))
    try:
        data = boundedjson.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ConfigError(f"not a report data file: {exc}", source=str(path)) from None
    if not isinstance(data, dict) or data.get("schema") != REPORT_SCHEMA:
        found = data.get("schema") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"schema {found!r}; expected {REPORT_SCHEMA!r}", source=str(path))
    return data


def render_to_file(directory: str | Path, out_file: str | Path) -> tuple[Path, str]:
    """Render the report of ``directory`` again from its JSON alone into ``out_file`` (one self-contained page).

    Returns:
        The page's path and a note ("" when every picture was drawn).

    Raises:
        ConfigError: The report data is missing or malformed.
        OutputError: ``out_file`` cannot be written.
    """
    from cellcal.core.calibration.report import write_bytes_atomic

    data = load_report_data(directory)
    pics, note = _pictures_or_note(data, Path(directory))
    return write_bytes_atomic(out_file, _page(data, pics, note, Path(directory))), note


def _page(data: Mapping[str, Any], pics: list[Picture], note: str, directory: Path) -> bytes:
    """The page's bytes.

    Raises:
        ConfigError: The data is malformed (naming the file).
    """
    from cellcal.core.report.fixed_html import FIXED_KIND, fixed_tables

    try:
        return render_html(data, pics, note, fixed_tables if data.get("kind") == FIXED_KIND else None).encode("utf-8")
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise ConfigError(f"malformed report data: {type(exc).__name__}: {exc}",
                          source=str(directory / REPORT_DATA_FILENAME)) from None
