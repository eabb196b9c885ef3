"""Poses with covariance, the relative pose of two cameras, and whether cameras agree on the plane (#40).

Pose parameterisation (that of the hand-eye result, ``core/handeye/model.py``; not a step on the
right): a pose ``T_a_b`` (rotation ``R``, translation ``t`` in metres) moves by ``delta = (phi, rho)``
to ``R' = Exp(phi) R``, ``t' = t + rho``: ``phi`` a rotation vector (rad) about the axes of the
parent frame *a*, applied on the LEFT, ``rho`` a shift (m) in frame *a*. The hand-eye mount
``T_flange_camera`` moves so (a turn about the flange axes, a translation in the flange frame), so
``PoseWithCovariance(estimate.mount, estimate.covariance[:6, :6])`` is the mount as estimated.

Plane parameterisation (the hand-eye model's plane): ``(tilt_a, tilt_b, offset)``: tilts (rad) about
the columns of ``tangent_basis(normal)`` and a change of ``offset_m`` (m), ``n' = Exp(B tilt) n``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellcal.core.geometry.planes import Plane, tangent_basis
from cellcal.devices.errors import CalibrationError
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]

__all__ = [
    "PlaneAgreement",
    "PlaneDifference",
    "PoseWithCovariance",
    "compose_jacobians",
    "cross_matrix",
    "inverse_jacobian",
    "perturb",
    "plane_agreement",
    "relative_pose",
    "transform_plane",
]

#: Largest asymmetry of a covariance, relative to its largest entry.
_SYMMETRY_TOLERANCE = 1e-9
#: Most negative eigenvalue of a semi-definite covariance, relative to its largest.
_PSD_TOLERANCE = 1e-10


def cross_matrix(v: FloatArray) -> FloatArray:
    """The cross-product matrix ``[v]x`` (``[v]x w = v x w``)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp(rotvec: FloatArray) -> FloatArray:
    """The rotation matrix of a rotation vector (rad), through :class:`Pose` (Rodrigues)."""
    return np.asarray(Pose.from_xyz_rotvec(np.zeros(3), rotvec).rotation_matrix, dtype=np.float64)


def _checked_covariance(value: ArrayLike, n: int, what: str, *, definite: bool) -> FloatArray:
    """``value`` as a symmetric n x n covariance (read-only copy).

    Raises:
        CalibrationError: If it is not n x n numbers, finite, symmetric, and positive (semi-)definite.
    """
    try:
        c = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what} must be a {n}x{n} matrix of numbers") from None
    if c.shape != (n, n):
        raise CalibrationError(f"{what} must be {n}x{n}, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise CalibrationError(f"{what} must be finite")
    scale = float(np.max(np.abs(c)))
    asym = float(np.max(np.abs(c - c.T)))
    if asym > _SYMMETRY_TOLERANCE * scale:
        raise CalibrationError(f"{what} must be symmetric (entries differ from their transpose by {asym:.3g})")
    c = 0.5 * (c + c.T)  # exactly symmetric
    eig = np.linalg.eigvalsh(c)
    if definite and not eig[0] > 0.0:
        raise CalibrationError(f"{what} must be positive definite (smallest eigenvalue {eig[0]:.3g})")
    if eig[0] < -_PSD_TOLERANCE * max(float(eig[-1]), 0.0):
        raise CalibrationError(f"{what} must be positive semi-definite (smallest eigenvalue {eig[0]:.3g})")
    c.setflags(write=False)
    return c


def perturb(pose: Pose, delta: ArrayLike) -> Pose:
    """``pose`` moved by a step of the parameterisation: ``(phi (rad, parent axes, left), rho (m, parent frame))``."""
    d = np.asarray(delta, dtype=np.float64).reshape(6)
    turned = Pose.from_xyz_rotvec(np.zeros(3), d[:3]) @ pose  # Exp(phi) R (its translation turned too: reset below)
    return turned.with_translation(pose.translation + d[3:])


def inverse_jacobian(pose: Pose) -> FloatArray:
    """6x6 first-order map of a step of ``pose`` to the step of ``pose.inv()`` (the parameterisation above)."""
    r_t = pose.rotation_matrix.T
    jac = np.zeros((6, 6))
    jac[:3, :3] = -r_t  # R^T Exp(-phi) = Exp(-R^T phi) R^T
    jac[3:, :3] = -r_t @ cross_matrix(pose.translation)  # -R^T Exp(-phi) t moves by -R^T [t]x phi
    jac[3:, 3:] = -r_t  # and by -R^T rho
    return jac


def compose_jacobians(a: Pose, b: Pose) -> tuple[FloatArray, FloatArray]:
    """The 6x6 first-order maps of steps of ``a`` and of ``b`` to the step of ``a @ b``."""
    r_a = a.rotation_matrix
    jac_a = np.eye(6)
    jac_a[3:, :3] = -cross_matrix(r_a @ b.translation)  # a's turn swings b's translation: phi x (R_a t_b)
    jac_b = np.zeros((6, 6))
    jac_b[:3, :3] = r_a  # b's turn, about b's parent axes, seen in a's parent frame: R_a phi_b
    jac_b[3:, 3:] = r_a  # b's shift likewise
    return jac_a, jac_b


@dataclass(frozen=True, eq=False)
class PoseWithCovariance:
    """A pose ``T_a_b`` and the 6x6 covariance of its step ``(phi rad, rho m)`` (module docstring).

    Attributes:
        pose: The transform (:class:`~cellcal.devices.pose.Pose`, metres).
        covariance: 6x6, rad² / rad m / m², symmetric positive semi-definite (read-only).
    """

    pose: Pose
    covariance: FloatArray

    def __post_init__(self) -> None:
        if not isinstance(self.pose, Pose):
            raise CalibrationError(f"PoseWithCovariance.pose must be a Pose, got {type(self.pose).__name__}")
        object.__setattr__(self, "covariance",
                           _checked_covariance(self.covariance, 6, "a pose covariance", definite=False))

    @classmethod
    def _of(cls, pose: Pose, covariance: FloatArray) -> PoseWithCovariance:
        """One with a propagated covariance (symmetrised; rounding may leave it a hair below semi-definite)."""
        out = cls.__new__(cls)
        c = 0.5 * (covariance + covariance.T)
        c.setflags(write=False)
        object.__setattr__(out, "pose", pose)
        object.__setattr__(out, "covariance", c)
        return out

    @classmethod
    def exact(cls, pose: Pose) -> PoseWithCovariance:
        """``pose`` with zero covariance."""
        return cls._of(pose, np.zeros((6, 6)))

    def inverse(self) -> PoseWithCovariance:
        """``T_b_a`` with the covariance propagated to first order."""
        jac = inverse_jacobian(self.pose)
        return PoseWithCovariance._of(self.pose.inv(), jac @ self.covariance @ jac.T)

    def compose(self, other: PoseWithCovariance, *, cross_covariance: ArrayLike | None = None
                ) -> PoseWithCovariance:
        """``self @ other`` (``T_a_b @ T_b_c = T_a_c``), the covariance propagated to first order.

        Args:
            other: The pose on the right.
            cross_covariance: 6x6 covariance of (this step, rows; ``other``'s step, columns);
                None: the two are independent.

        Raises:
            CalibrationError: If ``cross_covariance`` is not 6x6 finite numbers or makes the
                pair's joint covariance not positive semi-definite.
        """
        jac_a, jac_b = compose_jacobians(self.pose, other.pose)
        cov = jac_a @ self.covariance @ jac_a.T + jac_b @ other.covariance @ jac_b.T
        if cross_covariance is not None:
            cross = _checked_cross(self.covariance, other.covariance, cross_covariance)
            both = jac_a @ cross @ jac_b.T  # the correlated part, and its transpose below
            cov = cov + both + both.T
        return PoseWithCovariance._of(self.pose @ other.pose, cov)

    def at_flange(self, flange: Pose, flange_cov: ArrayLike | None = None) -> PoseWithCovariance:
        """This mount ``T_flange_camera`` as ``T_base_camera`` at the flange pose ``T_base_flange``.

        Args:
            flange: The arm's ``T_base_flange``.
            flange_cov: 6x6 covariance of the flange pose's step (turn about the base axes, rad;
                shift in the base frame, m), independent of the mount; None: exact.
        """
        first = (PoseWithCovariance.exact(flange) if flange_cov is None
                 else PoseWithCovariance(flange, np.asarray(flange_cov, dtype=np.float64)))
        return first.compose(self)

    def half_widths(self, confidence: float = 0.95) -> tuple[FloatArray, FloatArray]:
        """Per-axis two-sided interval half-widths at ``confidence``: (turn about the parent x, y, z, rad; shift, m).

        Raises:
            CalibrationError: If ``confidence`` is not in (0, 1).
        """
        z = NormalDist().inv_cdf(0.5 + _checked_confidence(confidence) / 2.0)  # sigmas per half-width
        sigma = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return z * sigma[:3], z * sigma[3:]


def _checked_confidence(confidence: float) -> float:
    if not 0.0 < float(confidence) < 1.0:
        raise CalibrationError(f"confidence must be in (0, 1), got {confidence}")
    return float(confidence)


def _checked_cross(cov_a: FloatArray, cov_b: FloatArray, cross: ArrayLike) -> FloatArray:
    """``cross`` as a 6x6 cross-covariance whose joint 12x12 with ``cov_a``, ``cov_b`` is semi-definite."""
    try:
        x = np.array(cross, dtype=np.float64)
    except (TypeError, ValueError):
        raise CalibrationError("a cross-covariance must be a 6x6 matrix of numbers") from None
    if x.shape != (6, 6) or not np.all(np.isfinite(x)):
        raise CalibrationError(f"a cross-covariance must be 6x6 and finite, got shape {x.shape}")
    _checked_covariance(np.block([[cov_a, x], [x.T, cov_b]]), 12, "the joint covariance with the cross-covariance",
                        definite=False)
    return x


def relative_pose(a: PoseWithCovariance, b: PoseWithCovariance, *, cross_covariance: ArrayLike | None = None
                  ) -> PoseWithCovariance:
    """Camera *b* in camera *a*'s frame: ``a⁻¹ @ b`` (``T_base_a⁻¹ @ T_base_b = T_a_b``) with covariance.

    Both poses share a parent frame (the base: a camera on the flange through
    :meth:`PoseWithCovariance.at_flange`); the result's step is in *a*'s frame.

    Args:
        a: Camera *a*'s pose in the common frame.
        b: Camera *b*'s pose in the common frame.
        cross_covariance: 6x6 covariance of (a's step, rows; b's step, columns); None: independent
            (``b``'s own covariance for ``a`` and ``b`` the same estimate gives zero).
    """
    jac = inverse_jacobian(a.pose)
    inv = PoseWithCovariance._of(a.pose.inv(), jac @ a.covariance @ jac.T)
    if cross_covariance is None:
        return inv.compose(b)
    cross = _checked_cross(a.covariance, b.covariance, cross_covariance)
    return inv.compose(b, cross_covariance=jac @ cross)  # Cov(J da, db) = J Cov(da, db)


def _plane_step(plane: Plane, step: FloatArray) -> Plane:
    """``plane`` moved by ``(tilt a, tilt b, offset)``: its normal turned across ``tangent_basis``, offset shifted."""
    basis = tangent_basis(np.asarray(plane.normal, dtype=np.float64))
    normal = np.asarray(plane.normal, dtype=np.float64) + basis @ step[:2]
    return Plane(normal / np.linalg.norm(normal), float(plane.offset_m) + float(step[2]))


def _plane_coordinates(plane: Plane, about: Plane) -> FloatArray:
    """``plane`` as ``(tilt a, tilt b, offset)`` about ``about`` (the same side of it)."""
    n = np.asarray(plane.normal, dtype=np.float64)
    sign = 1.0 if float(n @ np.asarray(about.normal)) >= 0 else -1.0
    basis = tangent_basis(np.asarray(about.normal, dtype=np.float64))
    return np.array([*(basis.T @ (sign * n)), sign * float(plane.offset_m) - float(about.offset_m)])


def transform_plane(plane: Plane, covariance: ArrayLike, pose: PoseWithCovariance) -> tuple[Plane, FloatArray]:
    """A plane given in a child frame, in its parent frame through ``pose`` (``T_parent_child``), with covariance.

    Args:
        plane: The plane in the child frame (e.g. a camera's measurement of the table).
        covariance: 3x3 of its ``(tilt a, tilt b, offset)``: turns of the normal about the axes of
            :func:`~cellcal.core.geometry.planes.tangent_basis` (rad) and the offset (m), as the hand-eye
            model's plane; independent of ``pose``'s.
        pose: The child's pose in the parent frame with its covariance.

    Returns:
        The plane in the parent frame and the 3x3 covariance of its ``(tilt a, tilt b, offset)`` about
        the returned plane's own tangent basis (first order, central differences).
    """
    cov_plane = _checked_covariance(covariance, 3, "plane covariance", definite=False)
    out = plane.transformed(pose.pose)
    jac = np.zeros((3, 9))
    for k in range(9):
        h = np.zeros(9)
        h[k] = 1e-7
        ends = [_plane_step(plane, s[6:]).transformed(perturb(pose.pose, s[:6])) for s in (h, -h)]
        jac[:, k] = (_plane_coordinates(ends[0], out) - _plane_coordinates(ends[1], out)) / 2e-7
    joint = np.zeros((9, 9))
    joint[:6, :6], joint[6:, 6:] = pose.covariance, cov_plane
    result: FloatArray = jac @ joint @ jac.T
    return out, 0.5 * (result + result.T)


@dataclass(frozen=True)
class PlaneDifference:
    """How far camera *b*'s plane is from camera *a*'s (or from the others' pooled plane).

    Attributes:
        camera_a, camera_b: The cameras (``camera_b`` "the others" for the outlier's figures).
        angle_rad: Angle between the normals (oriented alike), rad.
        offset_m: *b*'s offset minus *a*'s, m (along the common orientation).
        chi2: Squared Mahalanobis distance of the difference (tilts, offset) over its covariance.
        p_value: Probability of a chi2 this large (3 dof) if both measure the same plane.
    """

    camera_a: str
    camera_b: str
    angle_rad: float
    offset_m: float
    chi2: float
    p_value: float

    @property
    def mahalanobis(self) -> float:
        """The Mahalanobis distance (square root of ``chi2``)."""
        return math.sqrt(self.chi2)


@dataclass(frozen=True)
class PlaneAgreement:
    """Whether the cameras' base-frame planes agree.

    Attributes:
        cameras: The cameras' names, as given.
        agree: Whether the joint test passes (``p_value >= 1 - confidence``).
        chi2, dof, p_value: The joint test: each plane from the pooled (inverse-covariance weighted) one.
        confidence: Level of the tests.
        pairs: Every pair's difference (for information: the decision is the joint test's).
        outlier: The one camera whose removal makes the rest agree (None: all agree, or no single one).
        outlier_difference: Its plane from the others' pooled one (None without an outlier).
    """

    cameras: tuple[str, ...]
    agree: bool
    chi2: float
    dof: int
    p_value: float
    confidence: float
    pairs: tuple[PlaneDifference, ...]
    outlier: str | None = None
    outlier_difference: PlaneDifference | None = None

    def message(self) -> str:
        """One line: the verdict and its figures (degrees and millimetres)."""
        if self.outlier_difference is not None:
            d = self.outlier_difference
            return (f"camera '{self.outlier}' disagrees: its plane is {_deg_mm(d, 'and')} from the others' "
                    f"(p = {d.p_value:.2g})")
        worst = max(self.pairs, key=lambda d: d.chi2)
        if self.agree:
            return (f"the {len(self.cameras)} cameras' planes agree (chi2 {self.chi2:.3g} over {self.dof} dof, "
                    f"p = {self.p_value:.2g}); largest difference '{worst.camera_a}'-'{worst.camera_b}': "
                    f"{_deg_mm(worst, ',')}")
        if len(self.cameras) == 2:
            return (f"cameras '{worst.camera_a}' and '{worst.camera_b}' disagree: their planes are "
                    f"{_deg_mm(worst, 'and')} apart (p = {worst.p_value:.2g}); with two cameras neither can be named")
        return (f"the {len(self.cameras)} cameras' planes disagree (p = {self.p_value:.2g}) and no single camera "
                f"explains it; largest difference '{worst.camera_a}'-'{worst.camera_b}': {_deg_mm(worst, ',')} "
                f"(p = {worst.p_value:.2g})")


def _deg_mm(d: PlaneDifference, joint: str) -> str:
    """``0.41 deg and 3.2 mm`` of a difference."""
    sep = " and" if joint == "and" else ","
    return f"{math.degrees(d.angle_rad):.2g} deg{sep} {1000.0 * abs(d.offset_m):.2g} mm"


def _chi2_sf(value: float, dof: int) -> float:
    from scipy.stats import chi2  # 0.3 s to import: only when a test runs

    return float(chi2.sf(value, dof))


def _aligned(planes: list[tuple[Plane, FloatArray]]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Each plane's (tilt a, tilt b, offset) from the planes' mean normal, their covariances, that normal.

    Normals are turned to the first one's side (a plane seen from the other side: ``-n``, ``-c``).
    Each plane's step is a turn ``v = B_i tilt`` (the same turn moves ``-n``) and an offset change;
    its tilts are carried to the mean normal's tangent basis by the turn between the normals.
    """
    first = planes[0][0].normal
    signs = [1.0 if float(p.normal @ first) >= 0.0 else -1.0 for p, _ in planes]
    mean = sum((s * p.normal for s, (p, _) in zip(signs, planes, strict=True)), np.zeros(3))
    n0 = mean / np.linalg.norm(mean)
    b0 = tangent_basis(n0)
    x, cov = np.zeros((len(planes), 3)), np.zeros((len(planes), 3, 3))
    for i, (s, (plane, c)) in enumerate(zip(signs, planes, strict=True)):
        n = s * plane.normal
        cross = np.cross(n0, n)
        w = cross / max(np.linalg.norm(cross), 1e-300) * math.atan2(np.linalg.norm(cross), float(n0 @ n))
        x[i] = [*(b0.T @ w), s * plane.offset_m]  # Exp(w) n0 = n: the hand-eye plane's step from (n0, 0)
        jac = np.zeros((3, 3))
        jac[:2, :2] = b0.T @ _exp(-w) @ tangent_basis(plane.normal)  # its tilts, carried to n0's basis
        jac[2, 2] = s  # the offset's sign goes with the normal's
        cov[i] = jac @ c @ jac.T
    return x, cov, n0


def _pooled(x: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray, float]:
    """The inverse-covariance weighted mean, its covariance, and the chi2 of the planes from it."""
    weights = np.linalg.inv(cov)  # (k, 3, 3) information of each
    mean_cov = np.linalg.inv(weights.sum(axis=0))
    mean = mean_cov @ np.einsum("kij,kj->i", weights, x)
    r = x - mean
    return mean, mean_cov, float(np.einsum("ki,kij,kj->", r, weights, r))


def _difference(names: tuple[str, str], xa: FloatArray, ca: FloatArray, xb: FloatArray, cb: FloatArray,
                n0: FloatArray) -> PlaneDifference:
    """The difference of two aligned planes (:func:`_aligned`) and its chi2 test (3 dof)."""
    b0 = tangent_basis(n0)
    na, nb = _exp(b0 @ xa[:2]) @ n0, _exp(b0 @ xb[:2]) @ n0  # the normals
    angle = math.atan2(float(np.linalg.norm(np.cross(na, nb))), float(na @ nb))  # exact near 0, unlike acos
    d = xb - xa
    chi2 = float(d @ np.linalg.solve(ca + cb, d))
    return PlaneDifference(names[0], names[1], angle, float(d[2]), chi2, _chi2_sf(chi2, 3))


def plane_agreement(planes: Mapping[str, tuple[Plane, ArrayLike]], *, confidence: float = 0.95
                    ) -> PlaneAgreement:
    """Test whether the cameras' estimates of the measuring plane in the base frame agree.

    The estimates are taken as independent. Joint test: each plane's chi2 from the pooled one,
    ``3 (k - 1)`` dof. When it fails with three or more cameras, each is left out in turn: if
    exactly one leaves the rest agreeing, it is named.

    Args:
        planes: Per camera, its base-frame plane (either orientation) and the 3x3 covariance of
            (tilt about ``tangent_basis(normal)`` columns, rad; offset, m), as the hand-eye plane.
        confidence: Level of the tests (they fail below ``p = 1 - confidence``).

    Raises:
        CalibrationError: Fewer than two cameras, a bad plane or covariance (naming the camera),
            or ``confidence`` not in (0, 1).
    """
    alpha = 1.0 - _checked_confidence(confidence)
    names = tuple(planes)
    if len(names) < 2:
        raise CalibrationError(f"the plane agreement needs at least two cameras, got {len(names)}")
    given = []
    for name in names:
        plane, cov = planes[name]
        if not isinstance(plane, Plane):
            raise CalibrationError(f"camera '{name}': expected a Plane, got {type(plane).__name__}")
        given.append((plane, _checked_covariance(cov, 3, f"camera '{name}': the plane covariance", definite=True)))
    x, cov, n0 = _aligned(given)
    pairs = tuple(_difference((names[i], names[j]), x[i], cov[i], x[j], cov[j], n0)
                  for i in range(len(names)) for j in range(i + 1, len(names)))
    _, _, chi2 = _pooled(x, cov)
    dof = 3 * (len(names) - 1)
    p_value = _chi2_sf(chi2, dof)
    result = PlaneAgreement(names, p_value >= alpha, chi2, dof, p_value, confidence, pairs)
    if result.agree or len(names) < 3:
        return result
    fits = []  # the cameras whose removal leaves the rest agreeing
    for m in range(len(names)):
        rest = [i for i in range(len(names)) if i != m]
        _, _, chi2_rest = _pooled(x[rest], cov[rest])
        if _chi2_sf(chi2_rest, 3 * (len(rest) - 1)) >= alpha:
            fits.append(m)
    if len(fits) != 1:
        return result
    m = fits[0]
    rest = [i for i in range(len(names)) if i != m]
    mean, mean_cov, _ = _pooled(x[rest], cov[rest])
    against = _difference((names[m], "the others"), x[m], cov[m], mean, mean_cov, n0)
    return PlaneAgreement(names, False, chi2, dof, p_value, confidence, pairs, names[m], against)
