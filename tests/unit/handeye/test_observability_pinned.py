"""The observability analysis on constructed Jacobians: the rank threshold at its exact boundary, the texts whole.

Each Jacobian is built with chosen singular values and null directions, so that what the
analysis must find is known without it: a singular value just above / just below the
1/UNOBSERVABLE_SIGMA = 10 per unit threshold, the relative 1e-10 threshold of a huge one,
null directions that are one parameter block or straddle the block-share and cosine limits.
The texts a user reads (what cannot be seen, the fix) are compared as whole strings.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.handeye.model import PARAMETERS
from cellcal.core.handeye.observability import (
    FIX_ALONG_PLANE,
    FIX_HEIGHT,
    FIX_PLAN,
    FIX_ROTATION,
    UNOBSERVABLE_SIGMA,
    Observability,
    UnseenDirection,
    analyse,
    axis_text,
)

ALL = list(range(9))
#: The plane normal seen from the flange at every pose: flange z (4 poses).
FACING_Z = np.tile([0.0, 0.0, 1.0], (4, 1))
ROT_X, ROT_Y, ROT_Z, MX, MY, MZ, TILT_A, TILT_B, OFFSET = range(9)


def diagonal(values: list[float], rows: int = 12) -> np.ndarray:
    """A (rows, len(values)) Jacobian whose singular values are exactly ``values``, column k scaled by values[k]."""
    jac = np.zeros((rows, len(values)))
    jac[np.arange(len(values)), np.arange(len(values))] = values
    return jac


def with_null(null: list[np.ndarray], seen_value: float = 1000.0, rows: int = 12) -> np.ndarray:
    """A Jacobian over the nine parameters whose null space is spanned by the (orthonormal) vectors ``null``."""
    basis = np.linalg.qr(np.column_stack([*null, np.eye(9)]))[0][:, :9]  # null first, then the rest
    basis[:, :len(null)] = np.column_stack(null)  # keep the given vectors themselves (QR may flip signs)
    s = np.full(9, seen_value)
    s[:len(null)] = 0.0
    left = np.linalg.qr(np.random.default_rng(0).normal(size=(rows, rows)))[0][:, :9]
    return left @ np.diag(s) @ basis.T


def unit(*pairs: tuple[int, float]) -> np.ndarray:
    """The 9-vector with the given (index, value) entries, normalised."""
    v = np.zeros(9)
    for i, x in pairs:
        v[i] = x
    return v / np.linalg.norm(v)


def signed(axis: tuple[float, float, float] | None, k: int) -> str:
    """``"flange x"``: an unseen line is named with its largest component positive, whatever sign the SVD gave."""
    assert axis is not None and axis[k] > 0
    return f"flange {'xyz'[k]}"


# ---------------------------------------------------------------------- the rank threshold
@pytest.mark.parametrize(("smallest", "rank"), [(10.0, 9), (10.0 * (1 + 1e-9), 9), (10.0 * (1 - 1e-9), 8),
                                                 (10.5, 9), (9.5, 8), (1.05, 8), (99.0, 9)])
def test_the_rank_threshold_is_1_over_the_unobservable_sigma_inclusive(smallest: float, rank: int) -> None:
    assert UNOBSERVABLE_SIGMA == 0.1
    values = [smallest, 900.0, 800.0, 700.0, 600.0, 500.0, 400.0, 300.0, 1000.0]
    report = analyse(diagonal(values), ALL, FACING_Z)
    assert report.rank == rank and report.n_parameters == 9 and report.observable is (rank == 9)
    assert report.singular_values == (1000.0, 900.0, 800.0, 700.0, 600.0, 500.0, 400.0, 300.0, smallest)
    assert report.condition == 1000.0 / smallest
    if rank == 8:  # the smallest column is mount_rot_x: named, with its fix
        (only,) = report.unseen
        assert only == UnseenDirection("rotation", only.axis, f"mount rotation about {signed(only.axis, 0)}",
                                       FIX_ROTATION)
        assert abs(only.axis[0]) == 1.0  # type: ignore[index]


@pytest.mark.parametrize(("middle", "rank"), [(100.0 * (1 + 1e-6), 9), (100.0 * (1 - 1e-6), 8), (99.0, 8),
                                               (101.0, 9), (15.0, 8)])
def test_a_huge_singular_value_raises_the_threshold_to_1e_minus_10_of_it(middle: float, rank: int) -> None:
    values = [1e12, 1000.0, 1000.0, 1000.0, middle, 1000.0, 1000.0, 1000.0, 1000.0]
    report = analyse(diagonal(values), ALL, FACING_Z)
    assert report.rank == rank
    assert report.condition == 1e12 / middle


def test_no_parameters_at_all_is_observable_with_no_singular_values() -> None:
    report = analyse(np.zeros((6, 0)), [], FACING_Z)
    assert (report.rank, report.n_parameters, report.singular_values, report.unseen) == (0, 0, (), ())
    assert report.observable and report.condition == math.inf


def test_the_null_space_lands_on_the_free_parameters_it_belongs_to() -> None:
    # the plane tilts are given: 7 columns (mount 0-5, plane offset); the plane offset's column is the weak one
    free = [0, 1, 2, 3, 4, 5, 8]
    report = analyse(diagonal([500.0, 500.0, 500.0, 500.0, 500.0, 500.0, 1.0]), free, FACING_Z)
    assert report.rank == 6 and report.n_parameters == 7
    assert report.unseen == (UnseenDirection("plane", None, "the plane's tilt or height in the base frame",
                                             "add poses at other inclinations, or give plane_tilt_a/b and "
                                             "plane_offset"),)
    # ... and the same weak column as mount_z (index 5 of the free list): a translation, not the plane
    report = analyse(diagonal([500.0, 500.0, 500.0, 500.0, 500.0, 1.0, 500.0]), free, FACING_Z)
    (only,) = report.unseen
    assert only.part == "translation" and only.what == f"mount translation along {signed(only.axis, 2)}"


# ---------------------------------------------------------------------- rotations, named
def test_a_rotation_about_the_plane_normal_is_named_so() -> None:
    report = analyse(with_null([unit((ROT_Z, 1.0))]), ALL, FACING_Z)
    (only,) = report.unseen
    assert only == UnseenDirection("rotation", only.axis, f"mount rotation about {signed(only.axis, 2)} "
                                   "(= the plane normal)", FIX_ROTATION)
    assert np.allclose(np.abs(only.axis), [0.0, 0.0, 1.0], atol=1e-12)  # type: ignore[arg-type]
    assert report.message() == (f"cannot see 1 of 9 parameters: {only.what}; fix: {FIX_PLAN}")
    assert report.message() == (f"cannot see 1 of 9 parameters: {only.what}; "
                                "fix: add a second inclination and rolls about the tool axis")


@pytest.mark.parametrize(("cos", "named"), [(0.981, True), (0.979, False)])
def test_the_plane_normal_is_named_above_a_cosine_of_0_98(cos: float, named: bool) -> None:
    normals = np.tile([math.sqrt(1 - cos * cos), 0.0, cos], (4, 1))
    (only,) = analyse(with_null([unit((ROT_Z, 1.0))]), ALL, normals).unseen
    assert only.what == f"mount rotation about {signed(only.axis, 2)}" + (" (= the plane normal)" if named else "")


def test_the_mean_normal_decides_not_one_pose() -> None:
    # two poses at +-30 deg about x: the mean normal is flange z, neither pose's normal is
    c, s = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    normals = np.array([[0.0, s, c], [0.0, -s, c]])
    (only,) = analyse(with_null([unit((ROT_Z, 1.0))]), ALL, normals).unseen
    assert only.what.endswith("(= the plane normal)")


@pytest.mark.parametrize(("tilt", "traded"), [(0.21, True), (0.19, False)])
def test_a_rotation_traded_with_the_plane_tilt_beyond_a_share_of_0_2(tilt: float, traded: bool) -> None:
    null = unit((ROT_Y, math.sqrt(1 - tilt * tilt)), (TILT_B, tilt))
    (only,) = analyse(with_null([null]), ALL, FACING_Z).unseen
    assert only.what == f"mount rotation about {signed(only.axis, 1)}" + (
        " (traded with the plane's tilt)" if traded else "")
    assert only.fix == FIX_ROTATION == "poses at a second inclination or rolled about the tool axis"


def test_a_negative_plane_tilt_share_counts_too() -> None:
    null = unit((ROT_Y, math.sqrt(1 - 0.3**2)), (TILT_A, -0.3))
    (only,) = analyse(with_null([null]), ALL, FACING_Z).unseen
    assert only.what.endswith(" (traded with the plane's tilt)")


def test_two_unseen_rotations_are_named_by_the_axis_across_them() -> None:
    report = analyse(with_null([unit((ROT_X, 1.0)), unit((ROT_Y, 1.0))]), ALL, FACING_Z)
    (only,) = report.unseen
    assert only.axis is None and only.part == "rotation" and only.fix == FIX_ROTATION
    assert only.what == "mount rotation about axes across flange z"  # a line named with its largest component > 0
    assert report.rank == 7 and report.message().startswith("cannot see 2 of 9 parameters: mount rotation about axes")


def test_three_unseen_rotations_are_any_axis() -> None:
    null = [unit((ROT_X, 1.0)), unit((ROT_Y, 1.0)), unit((ROT_Z, 1.0), (TILT_A, 1.0))]
    (only,) = analyse(with_null(null), ALL, FACING_Z).unseen
    assert only == UnseenDirection("rotation", None, "mount rotation about any axis (traded with the plane's tilt)",
                                   FIX_ROTATION)


def test_a_rotation_share_below_0_2_is_not_a_rotation() -> None:
    # a null direction that is mostly mount translation along x with a 0.19 share of rotation about z
    null = unit((MX, math.sqrt(1 - 0.19**2)), (ROT_Z, 0.19))
    (only,) = analyse(with_null([null]), ALL, FACING_Z).unseen
    assert only.part == "translation"
    null = unit((MX, math.sqrt(1 - 0.21**2)), (ROT_Z, 0.21))
    assert [d.part for d in analyse(with_null([null]), ALL, FACING_Z).unseen] == ["rotation", "translation"]


# ---------------------------------------------------------------------- translations, named
@pytest.mark.parametrize(("share", "height"), [(0.23, True), (0.2, False)])
def test_the_height_trade_needs_a_product_of_shares_above_0_2(share: float, height: bool) -> None:
    # null = t e_mz + o e_offset: the translation that moves with the height has the length t * o
    o = share
    t = math.sqrt(1 - o * o)
    (only,) = analyse(with_null([unit((MZ, t), (OFFSET, o))]), ALL, FACING_Z).unseen
    assert (" vs the plane's height" in only.what) is height
    assert only.fix == (FIX_HEIGHT if height else FIX_ALONG_PLANE)


def test_the_height_and_a_sideways_translation_are_named_apart() -> None:
    report = analyse(with_null([unit((MZ, 1.0), (OFFSET, 1.0)), unit((MX, 1.0))]), ALL, FACING_Z)
    height, side = report.unseen
    assert height.what == f"mount translation along {signed(height.axis, 2)} vs the plane's height"
    assert side == UnseenDirection("translation", side.axis,
                                   f"mount translation along {signed(side.axis, 0)} (parallel to the plane)",
                                   FIX_ALONG_PLANE)
    assert np.allclose(np.abs(side.axis), [1.0, 0.0, 0.0], atol=1e-9)  # type: ignore[arg-type]
    # two unseen directions: the plane_offset hint is not offered
    assert report.message() == (f"cannot see 2 of 9 parameters: {height.what}; {side.what}; "
                                "fix: add a second inclination and rolls about the tool axis")


@pytest.mark.parametrize(("cos", "flat"), [(0.019, True), (0.021, False), (-0.021, False)])
def test_parallel_to_the_plane_below_a_cosine_of_0_02_at_every_pose(cos: float, flat: bool) -> None:
    # one pose sees the x translation at a cosine ``cos``, the others edge-on
    normals = np.array([[cos, 0.0, math.sqrt(1 - cos * cos)], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    (only,) = analyse(with_null([unit((MX, 1.0))]), ALL, normals).unseen
    assert only.what == f"mount translation along {signed(only.axis, 0)}" + (" (parallel to the plane)" if flat else "")
    assert only.fix == FIX_ALONG_PLANE == ("poses tilted toward that axis (a second inclination, several rolls "
                                           "about the tool axis)")


def test_two_unseen_translations_are_named_by_the_axis_across_them() -> None:
    (only,) = analyse(with_null([unit((MX, 1.0)), unit((MY, 1.0))]), ALL, FACING_Z).unseen
    assert only.axis is None and only.fix == FIX_ALONG_PLANE
    assert only.what == "mount translation across flange z (parallel to the plane)"


def test_three_unseen_translations_are_every_direction() -> None:
    (only,) = analyse(with_null([unit((MX, 1.0)), unit((MY, 1.0)), unit((MZ, 1.0))]), ALL, FACING_Z).unseen
    assert only == UnseenDirection("translation", None, "mount translation in every direction", FIX_ALONG_PLANE)


def test_a_translation_share_below_0_2_after_the_height_is_dropped() -> None:
    # two null vectors: the height trade, and one whose sideways translation share is 0.19 (rest: plane tilt)
    side = unit((MX, 0.19), (TILT_A, math.sqrt(1 - 0.19**2)))
    report = analyse(with_null([unit((MZ, 1.0), (OFFSET, 1.0)), side]), ALL, FACING_Z)
    assert [d.what for d in report.unseen][-1].endswith("vs the plane's height")
    side = unit((MX, 0.25), (TILT_A, math.sqrt(1 - 0.25**2)))
    report = analyse(with_null([unit((MZ, 1.0), (OFFSET, 1.0)), side]), ALL, FACING_Z)
    assert report.unseen[-1].what.endswith("(parallel to the plane)")


def test_an_observable_report_in_words_and_json() -> None:
    report = analyse(diagonal([1000.0, 900.0, 800.0, 700.0, 600.0, 500.0, 400.0, 300.0, 250.0]), ALL, FACING_Z)
    assert report.message() == "all 9 parameters observable (condition 4)"
    assert report.to_dict() == {"rank": 9, "n_parameters": 9, "observable": True, "condition": 4.0,
                                "singular_values": [1000.0, 900.0, 800.0, 700.0, 600.0, 500.0, 400.0, 300.0, 250.0],
                                "unobservable": []}


def test_an_unseen_direction_in_json() -> None:
    assert UnseenDirection("rotation", (0.0, 0.0, 1.0), "w", "f").to_dict() == {
        "part": "rotation", "axis_flange": [0.0, 0.0, 1.0], "what": "w", "fix": "f"}
    assert UnseenDirection("rotation", None, "w", "f").to_dict()["axis_flange"] is None


def test_a_height_with_other_unseen_directions_offers_no_plane_offset_hint() -> None:
    height = UnseenDirection("translation", (0.0, 0.0, 1.0), "mount translation along flange z vs the plane's height",
                             FIX_HEIGHT)
    other = UnseenDirection("rotation", None, "mount rotation about any axis", FIX_ROTATION)
    report = Observability(7, 9, math.inf, (0.0,) * 9, (height, other))
    assert report.message() == ("cannot see 2 of 9 parameters: mount translation along flange z vs the plane's "
                                "height; mount rotation about any axis; fix: add a second inclination and rolls "
                                "about the tool axis")
    assert Observability(9, 9, 12.345, (1.0,) * 9, ()).message() == "all 9 parameters observable (condition 12.3)"


# ---------------------------------------------------------------------- axis_text
@pytest.mark.parametrize(("axis", "text"), [
    ((1.0, 0.0, 0.0), "flange x"), ((0.0, -1.0, 0.0), "flange -y"), ((0.0, 0.0, 1.0), "flange z"),
    ((0.0, 0.0, -0.9995), "flange -z"), ((0.0, 0.9991, 0.0), "flange y"),
    ((0.0, 0.999, 0.0447), "flange (0.00,1.00,0.04)"),
    ((0.26, 0.0, 0.97), "flange (0.26,0.00,0.97)"), ((-0.001, -0.6, -0.8), "flange (0.00,-0.60,-0.80)"),
])
def test_axis_text(axis: tuple[float, float, float], text: str) -> None:
    assert axis_text(np.array(axis)) == text


def test_axis_text_in_another_frame() -> None:
    assert axis_text(np.array([0.0, 0.0, -1.0]), "base") == "base -z"
    assert axis_text(np.array([0.6, 0.0, 0.8]), "base") == "base (0.60,0.00,0.80)"


def test_the_parameter_order_the_null_space_relies_on() -> None:
    assert PARAMETERS[ROT_X] == "mount_rot_x" and PARAMETERS[OFFSET] == "plane_offset"


# ---------------------------------------------------------------------- condition, few rows, the height fix
def test_the_condition_is_the_ratio_when_every_value_is_seen() -> None:
    # the smallest singular value 20 is above the threshold of 10: seen, and the condition is 1000 / 20
    report = analyse(diagonal([1000.0] * 8 + [20.0]), ALL, FACING_Z)
    assert report.observable and report.condition == 50.0 and report.to_dict()["condition"] == 50.0


def test_an_exact_zero_singular_value_gives_an_infinite_condition_without_a_division_warning() -> None:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a division by the zero would warn
        report = analyse(diagonal([1000.0] * 8 + [0.0]), ALL, FACING_Z)
    assert report.singular_values[-1] == 0.0 and report.condition == math.inf
    assert report.to_dict()["condition"] is None  # JSON has no infinity


def test_fewer_residuals_than_parameters_still_name_nine_singular_values() -> None:
    report = analyse(diagonal([300.0, 200.0], rows=2) @ np.eye(2, 9), ALL, FACING_Z)
    assert (report.rank, report.n_parameters) == (2, 9)
    assert report.singular_values == (300.0, 200.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert not report.observable and report.unseen


def test_a_plan_that_trades_only_the_mount_height_with_the_plane_height_is_told_to_give_the_plane_offset() -> None:
    report = analyse(with_null([unit((MZ, 1.0), (OFFSET, 1.0))]), ALL, FACING_Z)
    (only,) = report.unseen
    assert only.what.endswith(" vs the plane's height")
    assert report.message() == (f"cannot see 1 of 9 parameters: {only.what}; fix: {FIX_PLAN}"
                                ", or give [handeye] given = [\"plane_offset\"]")
