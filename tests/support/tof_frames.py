"""An independent ToF frame generator for testing the full-frame fit.

It shares no code with ``cellcal.sims``: its own pinhole model (no distortion, principal
point at the image centre), its own ray casting of a plane (or two half-planes: a roof, a
step, a crease) and of oriented 3D boxes, range noise drawn along each ray, random
dropout, mixed ("flying") pixels where a pixel and its optical spill straddle a depth edge
(amplitude-weighted mix of the surfaces it sees, from a supersampled render blurred by a
Gaussian point-spread function given in degrees of view, so the band scales with the
resolution), and a multipath-like range bias growing toward the image border.

Everything is in the camera frame (OpenCV: x right, y down, z forward), metres. The
plane is placed by the distance along the optical axis to it and the camera's tilts
about its x and y axes (``Plane.tilt_about_x_rad`` convention). In-plane coordinates
``(u, v)`` are measured from where the optical axis meets the plane, ``u`` along the
image's x direction and ``v`` along its y direction.

Use :func:`render` once per scene (the noise-free geometry, mixing and bias included)
and :func:`draw` for each noisy frame; :func:`make_frame` does both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from cellcal.core.geometry.planes import Plane
from cellcal.devices.types import Frame, Intrinsics

F64 = NDArray[np.float64]

#: Resolutions the tests sweep (width, height): ToF sensors from 224x172 to 1280x800, and an odd one.
RESOLUTIONS = ((224, 172), (101, 77), (640, 480), (1280, 800))


@dataclass(frozen=True)
class ToFBox:
    """A box standing on the plane.

    Attributes:
        center_uv_m: Footprint centre in plane coordinates (u, v), metres.
        size_m: Edge lengths along the box's u, v and the plane normal, metres.
        yaw_deg: Rotation about the plane normal, degrees.
        reflectivity: Relative amplitude of its return (the table is 1).
    """

    center_uv_m: tuple[float, float]
    size_m: tuple[float, float, float]
    yaw_deg: float = 0.0
    reflectivity: float = 1.0


@dataclass(frozen=True)
class ToFSetup:
    """A scene and a camera.

    Attributes:
        width, height: Image size, pixels.
        fov_deg: Horizontal and vertical field of view, degrees.
        distance_m: Distance along the optical axis to the (base) plane, metres.
        tilt_x_deg, tilt_y_deg: Camera tilts about its x and y axes from the perpendicular view.
        noise_1m_m: Range-noise sigma at 1 m and normal incidence, metres (0: noise-free).
        noise_exponent: ``sigma = noise_1m_m * range**e / sqrt(cos incidence)``.
        quantisation_m: Range step, metres (0: none).
        dropout: Probability that a pixel is invalid at random.
        max_range_m: Farther returns are invalid.
        grazing_deg: Returns at a larger angle between ray and surface normal are invalid.
        boxes: Boxes on the plane.
        mixed: Mix the returns of pixels near depth edges (flying pixels).
        psf_deg: Sigma of the Gaussian spill of the optics, degrees of view.
        flying: Probability that a pixel straddling a depth edge (its 3x3 neighbourhood
            spans more than 2 cm of range) returns a range drawn uniformly between the
            nearest and the farthest range of that neighbourhood (drawn per frame).
        supersample: Sub-rays per pixel along each axis for the mixing (odd).
        border_bias_m: Range bias (longer) at the image corners, growing with the squared
            distance from the image centre (a multipath-like field).
        surface: ``plane``, or two half-planes meeting at ``u = split_u_m``: ``roof``
            (both halves tilted by ``surface_param`` degrees toward the camera),
            ``crease`` (the half u > split tilted by ``surface_param`` degrees) or
            ``step`` (the half u > split raised by ``surface_param`` metres).
        surface_param: Degrees (roof, crease) or metres (step).
        split_u_m: Where the two halves meet, plane coordinate u, metres.
    """

    width: int = 224
    height: int = 172
    fov_deg: tuple[float, float] = (60.0, 45.0)
    distance_m: float = 0.6
    tilt_x_deg: float = 10.0
    tilt_y_deg: float = 0.0
    noise_1m_m: float = 0.0032
    noise_exponent: float = 1.5
    quantisation_m: float = 0.0
    dropout: float = 0.01
    max_range_m: float = 4.0
    grazing_deg: float = 82.0
    boxes: tuple[ToFBox, ...] = ()
    mixed: bool = True
    psf_deg: float = 0.1
    flying: float = 0.0
    supersample: int = 3
    border_bias_m: float = 0.0
    surface: Literal["plane", "roof", "crease", "step"] = "plane"
    surface_param: float = 0.0
    split_u_m: float = 0.0
    _cache: dict[str, object] = field(default_factory=dict, compare=False, repr=False)

    # ------------------------------------------------------------------ camera
    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics reproducing the field of view, principal point at the centre."""
        fx = (self.width / 2) / math.tan(math.radians(self.fov_deg[0]) / 2)
        fy = (self.height / 2) / math.tan(math.radians(self.fov_deg[1]) / 2)
        return Intrinsics(self.width, self.height, fx, fy, (self.width - 1) / 2, (self.height - 1) / 2)

    def rotation(self) -> F64:
        """Columns: the plane's u, v axes and its normal (toward the camera), camera frame."""
        a, b = math.radians(self.tilt_x_deg), math.radians(self.tilt_y_deg)
        rx = np.array([[1, 0, 0], [0, math.cos(a), math.sin(a)], [0, -math.sin(a), math.cos(a)]])  # Rx(-a)
        ry = np.array([[math.cos(b), 0, -math.sin(b)], [0, 1, 0], [math.sin(b), 0, math.cos(b)]])   # Ry(-b)
        r = rx @ ry
        return np.column_stack([r @ [1.0, 0, 0], r @ [0, 1.0, 0], r @ [0, 0, -1.0]])

    def truth(self) -> Plane:
        """The base plane (camera frame, normal toward the camera)."""
        n = self.rotation()[:, 2]
        return Plane(n, -float(n @ [0.0, 0.0, self.distance_m]))

    def origin(self) -> F64:
        """Where the optical axis meets the base plane, camera frame."""
        return np.array([0.0, 0.0, self.distance_m])


# ---------------------------------------------------------------------- ray casting
def _rays(setup: ToFSetup, s: int) -> F64:
    """Unit rays (H*s, W*s, 3) of an s x s grid of sub-pixels per pixel."""
    intr = setup.intrinsics()
    off = (np.arange(s) + 0.5) / s - 0.5
    x = (np.arange(setup.width)[:, None] + off[None, :]).reshape(-1)
    y = (np.arange(setup.height)[:, None] + off[None, :]).reshape(-1)
    xx = (x - intr.cx) / intr.fx
    yy = (y - intr.cy) / intr.fy
    r = np.empty((yy.size, xx.size, 3))
    r[..., 0] = xx[None, :]
    r[..., 1] = yy[:, None]
    r[..., 2] = 1.0
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    return r


def _half_planes(setup: ToFSetup) -> list[tuple[F64, float, F64, float, float]]:
    """Surfaces as (normal, offset, axis a, lo, hi): valid where ``lo <= a·p + c <= hi`` (c folded in)."""
    rot = setup.rotation()
    eu, n = rot[:, 0], rot[:, 2]
    o = setup.origin()
    q = o + setup.split_u_m * eu                      # a point on the split line (along ev)
    su = float(eu @ q)                                 # u-coordinate of the line: eu·p = su
    inf = math.inf

    def plane(normal: F64, point: F64) -> tuple[F64, float]:
        return normal, -float(normal @ point)

    def tilted(angle_deg: float) -> F64:               # n rotated about ev (toward +u when positive)
        a = math.radians(angle_deg)
        return math.cos(a) * n - math.sin(a) * eu

    if setup.surface == "plane":
        nn, d = plane(n, o)
        return [(nn, d, eu, -inf, inf)]
    if setup.surface == "roof":                        # both halves rise toward the ridge
        left, right = plane(tilted(setup.surface_param), q), plane(tilted(-setup.surface_param), q)
        return [(*left, eu, -inf, su), (*right, eu, su, inf)]
    if setup.surface == "crease":
        left, right = plane(n, q), plane(tilted(setup.surface_param), q)
        return [(*left, eu, -inf, su), (*right, eu, su, inf)]
    if setup.surface == "step":
        h = setup.surface_param
        low, high = plane(n, q), plane(n, q + h * n)
        riser = plane(-eu if h > 0 else eu, q)
        lo_w, hi_w = float(n @ q) + min(h, 0.0), float(n @ q) + max(h, 0.0)
        return [(*low, eu, -inf, su), (*high, eu, su, inf), (riser[0], riser[1], n, lo_w, hi_w)]
    raise ValueError(f"unknown surface {setup.surface!r}")


def _cast(setup: ToFSetup, rays: F64) -> tuple[F64, F64, NDArray[np.int16]]:
    """Range, |cos incidence| and surface label (-1 miss, 0.. half-planes, 10+k box k) of each ray."""
    shape = rays.shape[:-1]
    r = rays.reshape(-1, 3)
    best = np.full(r.shape[0], np.inf)
    cos = np.zeros(r.shape[0])
    label = np.full(r.shape[0], -1, dtype=np.int16)
    for k, (nn, d, axis, lo, hi) in enumerate(_half_planes(setup)):
        rn = r @ nn
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -d / rn
        a = (r @ axis) * t
        hit = (t > 1e-9) & (a >= lo) & (a <= hi) & (t < best)
        best[hit], cos[hit], label[hit] = t[hit], np.abs(rn[hit]), k
    rot = setup.rotation()
    eu, ev, n = rot[:, 0], rot[:, 1], rot[:, 2]
    best, cos, label = best.reshape(shape), cos.reshape(shape), label.reshape(shape)
    gx = rays[0, :, 0] / rays[0, :, 2]                 # normalised image coordinates of the grid
    gy = rays[:, 0, 1] / rays[:, 0, 2]
    for k, box in enumerate(setup.boxes):
        yaw = math.radians(box.yaw_deg)
        ax = np.stack([math.cos(yaw) * eu + math.sin(yaw) * ev, -math.sin(yaw) * eu + math.cos(yaw) * ev, n])
        half = np.asarray(box.size_m) / 2
        centre = setup.origin() + box.center_uv_m[0] * eu + box.center_uv_m[1] * ev + half[2] * n
        corners = centre + (np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * half) @ ax
        if np.all(corners[:, 2] > 1e-6):               # only the rays of the box's image rectangle
            cx, cy = corners[:, 0] / corners[:, 2], corners[:, 1] / corners[:, 2]
            c0, c1 = np.searchsorted(gx, cx.min()) - 1, np.searchsorted(gx, cx.max()) + 1
            r0, r1 = np.searchsorted(gy, cy.min()) - 1, np.searchsorted(gy, cy.max()) + 1
            c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, shape[1]), min(r1, shape[0])
        else:
            r0, r1, c0, c1 = 0, shape[0], 0, shape[1]
        if r1 <= r0 or c1 <= c0:
            continue
        sub = rays[r0:r1, c0:c1].reshape(-1, 3)
        o_local = ax @ (-centre)                       # camera origin in box axes
        dl = sub @ ax.T                                # ray directions in box axes
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - o_local) / dl
            t2 = (half - o_local) / dl
        tmin = np.minimum(t1, t2)
        t_in = tmin.max(axis=1)
        t_out = np.maximum(t1, t2).min(axis=1)
        face = tmin.argmax(axis=1)
        b = best[r0:r1, c0:c1].reshape(-1)
        hit = (t_in <= t_out) & (t_in > 1e-9) & (t_in < b)
        b[hit] = t_in[hit]
        best[r0:r1, c0:c1] = b.reshape(r1 - r0, -1)
        lab = label[r0:r1, c0:c1].reshape(-1)
        lab[hit] = 10 + k
        label[r0:r1, c0:c1] = lab.reshape(r1 - r0, -1)
        cs = cos[r0:r1, c0:c1].reshape(-1)
        cs[hit] = np.abs(dl[hit, face[hit]])
        cos[r0:r1, c0:c1] = cs.reshape(r1 - r0, -1)
    return best, cos, label


# ---------------------------------------------------------------------- rendering
@dataclass(frozen=True)
class Render:
    """The noise-free measurement of a setup: what :func:`draw` adds noise and dropout to.

    Attributes:
        rays: Unit rays (H, W, 3).
        range_m: Measured range without noise (mixing and border bias included), NaN where invalid.
        true_range_m: Range of the surface the pixel's centre sees, NaN where invalid.
        cos_incidence: |cos| of the angle between ray and surface normal.
        label: Surface label of the pixel centre (-1 miss, 0.. half-planes, 10+k box k).
        mixed: True where the return mixes several surfaces.
        valid: Geometrically valid pixels (in range, not grazing).
        near_m, far_m: Nearest and farthest noise-free range of each pixel's 3x3
            neighbourhood (the interval a flying pixel's range is drawn from).
    """

    setup: ToFSetup
    rays: F64
    range_m: F64
    true_range_m: F64
    cos_incidence: F64
    label: NDArray[np.int16]
    mixed: NDArray[np.bool_]
    valid: NDArray[np.bool_]
    near_m: F64
    far_m: F64

    def on_base_plane(self, tol_m: float = 0.0) -> NDArray[np.bool_]:
        """Valid pixels whose measured (noise-free) point lies on the base plane within ``tol_m``."""
        pl = self.setup.truth()
        dist = np.abs(np.einsum("hwk,k->hw", self.rays, pl.normal) * self.range_m + pl.offset_m)
        return self.valid & (np.nan_to_num(dist, nan=np.inf) <= tol_m) & (self.label < 10)


def _mix(setup: ToFSetup, t: F64, cos: F64, label: NDArray[np.int16]) -> tuple[F64, NDArray[np.bool_]]:
    """Amplitude-weighted mix of each pixel's sub-rays, blurred by the PSF; and where it matters."""
    s = setup.supersample
    sub_rays = _rays(setup, s)
    ts, cs, ls = _cast(setup, sub_rays)
    refl = np.ones(ls.shape)
    for k, box in enumerate(setup.boxes):
        refl[ls == 10 + k] = box.reflectivity
    ok = np.isfinite(ts) & (ls >= 0)
    amp = np.where(ok, refl * cs / np.where(ok, ts, 1.0) ** 2, 0.0)   # return amplitude ~ cos / range^2
    f = setup.intrinsics().fx
    sigma_sub = math.radians(setup.psf_deg) * f * s                     # PSF sigma in sub-pixels
    at = ndimage.uniform_filter(amp * np.where(ok, ts, 0.0), s, mode="constant")
    a = ndimage.uniform_filter(amp, s, mode="constant")
    if sigma_sub > 0:
        at = ndimage.gaussian_filter(at, sigma_sub, mode="constant", truncate=3.0)
        a = ndimage.gaussian_filter(a, sigma_sub, mode="constant", truncate=3.0)
    c = s // 2
    with np.errstate(invalid="ignore", divide="ignore"):
        mixed_t = (at / a)[c::s, c::s]
    radius = s // 2 + math.ceil(3.0 * sigma_sub)                        # kernel support, sub-pixels
    size = 2 * radius + 1
    differs = ndimage.maximum_filter(ls, size) != ndimage.minimum_filter(ls, size)
    band = differs[c::s, c::s]
    return np.where(band, mixed_t, t), band


def render(setup: ToFSetup) -> Render:
    """The noise-free measurement of ``setup`` (cached on the setup)."""
    cached = setup._cache.get("render")
    if isinstance(cached, Render):
        return cached
    rays = _rays(setup, 1)
    t, cos, label = _cast(setup, rays)
    measured, mixed = _mix(setup, t, cos, label) if setup.mixed else (t, np.zeros(t.shape, bool))
    intr = setup.intrinsics()
    if setup.border_bias_m:
        x = (np.arange(setup.width) - intr.cx) / intr.fx
        y = (np.arange(setup.height) - intr.cy) / intr.fy
        rho2 = x[None, :] ** 2 + y[:, None] ** 2
        measured = measured + setup.border_bias_m * rho2 / rho2.max()   # longer toward the border
    valid = (label >= 0) & np.isfinite(measured) & (t <= setup.max_range_m)
    valid &= cos >= math.cos(math.radians(setup.grazing_deg))
    finite = np.where(valid, measured, np.nan)
    near = ndimage.minimum_filter(np.where(valid, measured, np.inf), 3, mode="nearest")
    far = ndimage.maximum_filter(np.where(valid, measured, -np.inf), 3, mode="nearest")
    out = Render(setup, rays, finite, np.where(valid, t, np.nan), cos, label, mixed & valid, valid, near, far)
    setup._cache["render"] = out
    return out


def draw(rend: Render, rng: np.random.Generator) -> Frame:
    """One noisy frame of a render: range noise along the ray, quantisation, random dropout."""
    st = rend.setup
    d = np.where(rend.valid, rend.range_m, 1.0)
    if st.noise_1m_m > 0:
        sigma = st.noise_1m_m * d ** st.noise_exponent / np.sqrt(np.maximum(rend.cos_incidence, 1e-6))
        d = d + sigma * rng.standard_normal(d.shape)
    if st.quantisation_m > 0:
        d = np.round(d / st.quantisation_m) * st.quantisation_m
    if st.flying > 0:
        edge = rend.valid & (rend.far_m - rend.near_m > 0.02) & (rng.random(d.shape) < st.flying)
        with np.errstate(invalid="ignore"):
            d = np.where(edge, rend.near_m + rng.random(d.shape) * (rend.far_m - rend.near_m), d)
    valid = rend.valid & (d > 0)
    if st.dropout > 0:
        valid &= rng.random(d.shape) >= st.dropout
    dist = np.where(valid, d, np.nan).astype(np.float32)
    xyz = (rend.rays * dist[..., None]).astype(np.float32)
    amp = np.where(valid, 1000.0 * rend.cos_incidence / np.where(valid, d, 1.0) ** 2, 0.0).astype(np.float32)
    return Frame(distance=dist, xyz=xyz, amplitude=amp, valid=valid, intrinsics=st.intrinsics(),
                 timestamp=0.0, sequence=0)


def make_frame(setup: ToFSetup, seed: int = 0) -> Frame:
    """:func:`render` then :func:`draw` with ``numpy.random.default_rng(seed)``."""
    return draw(render(setup), np.random.default_rng(seed))


# ---------------------------------------------------------------------- scenes
def scattered_boxes(fraction: float, seed: int, setup: ToFSetup | None = None, max_boxes: int = 40,
                    size_range_m: tuple[float, float] = (0.05, 0.14),
                    height_range_m: tuple[float, float] = (0.03, 0.1)) -> tuple[ToFBox, ...]:
    """Random boxes added until they hide about ``fraction`` of the plane's valid pixels.

    Boxes lie inside the visible footprint of the plane; each is accepted only if it
    raises the hidden fraction (sizes, heights and yaws drawn from ``seed``).
    """
    base = setup or ToFSetup()
    rng = np.random.default_rng(seed)
    w = min(base.width, 160)                           # the hidden fraction does not depend on the resolution
    low = {**_fields(base), "width": w, "height": max(1, round(base.height * w / base.width)), "mixed": False}
    rend0 = render(ToFSetup(**{**low, "boxes": ()}))
    foot = rend0.rays[rend0.valid] * rend0.true_range_m[rend0.valid][:, None] - base.origin()
    rot = base.rotation()
    uv = foot @ rot[:, :2]
    lo, hi = np.percentile(uv, 5, axis=0), np.percentile(uv, 95, axis=0)
    boxes: list[ToFBox] = []
    hidden = 0.0
    for _ in range(max_boxes * 4):
        if hidden >= fraction or len(boxes) >= max_boxes:
            break
        size = rng.uniform(*size_range_m, 2)
        box = ToFBox((float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1]))),
                     (float(size[0]), float(size[1]), float(rng.uniform(*height_range_m))),
                     float(rng.uniform(0, 90)), float(rng.uniform(0.3, 1.5)))
        trial = ToFSetup(**{**low, "boxes": (*boxes, box)})
        r = render(trial)
        h = 1.0 - float(np.count_nonzero(r.valid & (r.label < 10))) / float(np.count_nonzero(rend0.valid))
        if h <= hidden + 0.005 or h > fraction + 0.05:
            continue
        boxes.append(box)
        hidden = h
    return tuple(boxes)


def _fields(setup: ToFSetup) -> dict[str, object]:
    return {k: getattr(setup, k) for k in ToFSetup.__dataclass_fields__ if k != "_cache"}


def with_(setup: ToFSetup, **changes: object) -> ToFSetup:
    """A copy of ``setup`` with some fields changed (and a fresh render cache)."""
    return ToFSetup(**{**_fields(setup), **changes})  # type: ignore[arg-type]
