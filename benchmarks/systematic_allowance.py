"""Honest before depthcal: do the full-frame fit's 95 % intervals cover the truth when the camera errs systematically?

Issue #39's target "Same sims without depthcal: 95 % intervals still cover the truth >= 90 %".
Synthetic stereo and ToF frames (tests/support/systematic_frames.py: independent of the sims) of a
plane at random heights (0.5-1.0 m) and tilts (up to 15 deg), each with its own systematic error
drawn within the camera's stated allowance (1-sigma: stereo f·B scale 1 %, disparity offset
0.1 px, a field of 0.5 px at the corner; ToF range scale 0.2 %, offset 5 mm, field 2 mm; the field
drawn from the fit's prior, six smooth shapes with independent coefficients, or as a radial bow alone):
the coverage of tilt x, tilt y and height by their 95 % intervals, with the allowance (the
default) and without it (the camera stating zero allowance: the intervals of noise alone), and
the mean 95 % half-widths either way. Also the time the allowance's budget adds to a fit.

Usage: ``python benchmarks/systematic_allowance.py [--seeds 50] [--field prior|bow|both]``. Prints PASS/FAIL for
coverage >= 90 %. Rationale: docs/adr/0059-systematic-allowance-and-error-budget.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cellcal.core.methods.fullframe import fit_full_frame
from cellcal.devices.systematic import SystematicError
from tests.support.systematic_frames import (
    stereo_frame,
    stereo_model,
    tof_frame,
    tof_model,
    truth_plane,
)

TARGET = 0.90
Z95 = 1.959963984540054


def _field(f: float, rng: np.random.Generator, field: str) -> tuple[float, ...]:
    """Coefficients of ``u, v, u², uv, v²`` of a field of 1-sigma ``f`` at the corner.

    ``bow``: a radial bow ``(u² + v²)/2`` alone; ``prior``: the fit's own prior (ADR 0059 "Amended"),
    the sum of the six shapes (bow, u², v², uv, u, v) with independent coefficients of sigma ``f/sqrt(6)``.
    """
    if field == "bow":
        bow = rng.normal(0.0, f)
        return (0.0, 0.0, bow / 2.0, 0.0, bow / 2.0)
    bow, u2, v2, uv, u, v = rng.normal(0.0, f / math.sqrt(6.0), 6)
    return (u, v, bow / 2.0 + u2, uv, bow / 2.0 + v2)


def _draw(kind: str, rng: np.random.Generator, field: str = "prior") -> SystematicError:
    """A systematic error drawn from the kind's default allowance (1-sigma per term; the field as ``field``)."""
    if kind == "stereo":
        s, o, f = stereo_model().allowance
        return SystematicError("stereo", fb_error=float(rng.normal(0.0, s)),
                               disparity_offset_px=float(rng.normal(0.0, o)), field_order=2,
                               field_coeffs=_field(f, rng, field))
    s, o, f = tof_model().allowance
    return SystematicError("tof", scale_error=float(rng.normal(0.0, s)), offset_m=float(rng.normal(0.0, o)),
                           field_order=2, field_coeffs=_field(f, rng, field))


def run(kind: str, seeds: int, field: str = "prior") -> dict[str, list[float]]:
    out: dict[str, list[float]] = {k: [] for k in (
        "cov_tx", "cov_ty", "cov_h", "cov0_tx", "cov0_ty", "cov0_h", "hw_t", "hw0_t", "hw_h", "hw0_h",
        "t_fit", "refused")}
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        plane = truth_plane(float(rng.uniform(0.5, 1.0)), float(rng.uniform(-15, 15)), float(rng.uniform(-15, 15)))
        error = _draw(kind, rng, field)
        truth = (plane.tilt_about_x_rad(), plane.tilt_about_y_rad(), plane.distance_along_optical_axis_m())
        for zero in (False, True):
            model = stereo_model(zero=zero) if kind == "stereo" else tof_model(zero=zero)
            make = stereo_frame if kind == "stereo" else tof_frame
            frame = make(plane, error, model, np.random.default_rng(seed))
            t0 = time.perf_counter()
            res = fit_full_frame(frame)
            if not zero:
                out["t_fit"].append(time.perf_counter() - t0)
            if not res.passed and not zero:
                out["refused"].append(1.0)
            p = "cov0_" if zero else "cov_"
            for key, est, val in (("tx", res.tilt_x, truth[0]), ("ty", res.tilt_y, truth[1]),
                                  ("h", res.height, truth[2])):
                out[p + key].append(float(est.interval[0] <= val <= est.interval[1]))
            hw = "hw0_" if zero else "hw_"
            out[hw + "t"].append(Z95 * max(res.tilt_x.sigma, res.tilt_y.sigma))
            out[hw + "h"].append(Z95 * res.height.sigma)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--field", choices=("prior", "bow", "both"), default="both",
                    help="the drawn field: the fit's prior (six shapes), a radial bow alone, or both in turn")
    args = ap.parse_args(argv)
    ok = True
    fields = ("prior", "bow") if args.field == "both" else (args.field,)
    for kind, field in ((k, f) for f in fields for k in ("stereo", "tof")):
        r = run(kind, args.seeds, field)

        def pct(k: str, r: dict[str, list[float]] = r) -> float:
            return 100.0 * statistics.fmean(r[k])

        print(f"{kind}: {args.seeds} planes, each with its own systematic error drawn within the allowance "
              f"(field: {'the six shapes of the prior' if field == 'prior' else 'a radial bow'})")
        print(f"  coverage of the 95 % intervals with the allowance: tilt x {pct('cov_tx'):.0f} %, "
              f"tilt y {pct('cov_ty'):.0f} %, height {pct('cov_h'):.0f} %")
        print(f"  ... without it (noise alone):                     tilt x {pct('cov0_tx'):.0f} %, "
              f"tilt y {pct('cov0_ty'):.0f} %, height {pct('cov0_h'):.0f} %")
        print(f"  mean 95 % half-width, tilt: {math.degrees(statistics.fmean(r['hw0_t'])):.4f} -> "
              f"{math.degrees(statistics.fmean(r['hw_t'])):.4f} deg; height: "
              f"{statistics.fmean(r['hw0_h']) * 1000:.3f} -> {statistics.fmean(r['hw_h']) * 1000:.2f} mm")
        print(f"  runs refused by a gate: {len(r['refused'])} of {args.seeds}; "
              f"median fit {statistics.median(r['t_fit']) * 1000:.0f} ms")
        worst = min(pct("cov_tx"), pct("cov_ty"), pct("cov_h")) / 100.0
        verdict = "PASS" if worst >= TARGET else "FAIL"
        ok &= worst >= TARGET
        print(f"  target coverage >= {TARGET:.0%}: {verdict}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
