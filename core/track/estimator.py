"""The recursive estimate of the mount and the base-frame plane from the frames of normal work (ADR 0040).

An iterated extended Kalman filter in information form over the nine hand-eye parameters
(:mod:`cellcal.core.handeye.model`): per accepted frame the Gauss-Newton step of
``|x - x_prev|²_Λ + |x|²_Π + |r(x)|²`` (``Λ`` the data's information so far, ``Π`` a weak
isotropic prior at the configured values, ``r`` the frame's whitened residual). A bounded
window of the latest accepted frames is relinearised about the estimate every 30 frames
and before a surprising frame is judged; frames leaving it join a quadratic prior
linearised about the estimate of that moment (a fixed-lag smoother). Which directions the
work has shown is decided from ``Λ`` with the hand-eye threshold (1-sigma below 0.1 rad /
0.1 m, :mod:`cellcal.core.handeye.observability`); only those get intervals, and the
reported values keep the configured ones along the others. The stated noise is tested
both ways per residual component on the normalised innovations of a bounded window
(:mod:`cellcal.core.handeye.noise`); a component with more residual than stated scales its
share of the covariance (a sandwich). A CUSUM on the same innovations detects a change
(:mod:`.detector`); the changed block is restarted from the frames after it. Memory is
bounded: 9x9 matrices and fixed-size windows. Its settings and what it reports are :mod:`.state`'s.

The frames are weighed by the fit's noise alone: the camera's systematic error and the arm's
absolute error do not change from frame to frame (or slowly), so in the weights they would
deafen the change detector. The reported intervals add them (ADR 0055, "Poses combined"): the
systematic allowance's terms, each a coefficient common to every frame, move the estimate by
``Λ⁺ Σ Jᵀ δr`` (accumulated as the information is), and the arm's stated accuracy its common
part as the hand-eye fit adds it.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import (
    MOUNT_ROTATION,
    MOUNT_TRANSLATION,
    PARAMETERS,
    PLANE_OFFSET,
    PLANE_TILT,
    PlaneModel,
    PlaneObservation,
)
from cellcal.core.handeye.noise import check_noise
from cellcal.core.handeye.observability import UNOBSERVABLE_SIGMA, analyse
from cellcal.core.track.detector import KIND_EITHER, KIND_MOUNT, KIND_PLANE, Cusum, Hypothesis, classify
from cellcal.core.track.linear import SYSTEMATIC_SLOTS, FrameRing, Frames, LinearModel
from cellcal.core.track.state import ChangeEvent, TrackSettings, TrackState, TrackStep
from cellcal.devices.pose import Pose

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
#: A parameter counts as seen when its share of the unseen subspace is below this.
SEEN_SHARE = 0.05
#: A change is tried again when the arm turned (rad) or moved (m) this much since the last try, or after
#: this many frames.
CLASSIFY_TURN_RAD = math.radians(0.5)
CLASSIFY_MOVE_M = 0.005
CLASSIFY_EVERY = 30
#: Frames in the noise test's window before the change test uses its scale.
MIN_NOISE_FRAMES = 30
#: A flange-frame plane normal is kept for naming unseen directions when it differs from the last kept by this, rad.
NORMAL_STEP_RAD = math.radians(1.0)


class Tracker:
    """Recursive estimate of the mount and the plane, with change detection (pure logic, no I/O).

    Args:
        nominal_mount: The configured ``T_flange_camera``.
        nominal_plane: The configured plane in the base frame (turned toward the camera at the first frame).
        settings: Noise, intervals, detector and windows (defaults: :class:`TrackSettings`).
        fixed: A camera fixed in the base frame (ADR 0061): its frames are fed at the identity flange pose
            and ``nominal_mount`` is its configured ``T_base_camera``. Its pose and the plane trade fully
            (one view), so a change's size also says how the plane moved in the camera's own frame
            (``view_tilt_deg``, ``view_shift_m``), the one thing that view measures (:meth:`view_plane`).
    """

    def __init__(self, nominal_mount: Pose, nominal_plane: Plane, settings: TrackSettings | None = None, *,
                 fixed: bool = False) -> None:
        self.settings = s = settings or TrackSettings()
        self.fixed = fixed
        self.nominal_mount = nominal_mount
        self.nominal_plane = nominal_plane
        self._lever = float(np.linalg.norm(nominal_mount.translation))  # the mount's lever for the arm's turn noise
        self._linear: LinearModel | None = None  # built at the first frame (plane orientation)
        self._weak = s.prior_sigma ** -2  # information of the isotropic prior per parameter
        self._x = np.zeros(9)  # parameter steps from the configured values
        self._info = np.zeros((9, 9))  # the data's information (JᵀJ so far: marginalised and in the window)
        self._window = FrameRing(s.window)  # the latest accepted frames, relinearised in the batch steps
        self._prior_info = np.zeros((9, 9))  # frames pushed out of the window: x'Λx - 2h'x, linearised when they left
        self._prior_h = np.zeros(9)
        # per systematic term: Σ Jᵀ δr over the frames (the prior's and the window's), as the information is kept
        self._sys_g = np.zeros((SYSTEMATIC_SLOTS, 9))
        self._prior_sys_g = np.zeros((SYSTEMATIC_SLOTS, 9))
        self._sys_keys: list[str] = []  # the allowance's terms in their slots, in order of first appearance
        # the information split by whitened residual component (normal across x2, offset) and a 4th part for
        # a restart's kept block: the noise test scales each part by its own component's measured noise
        self._parts = np.zeros((4, 9, 9))
        self._prior_parts = np.zeros((4, 9, 9))
        self._since_batch = 0  # accepted frames since the last batch step
        self._cusum = Cusum(s.detector_reference, s.detector_clip, s.detector_threshold)
        self._recent: deque[tuple[Frames, float]] = deque(maxlen=s.change_window)  # latest frames and their chi2
        self._after: deque[Frames] | None = None  # frames after a detected change, until it is classified
        self._classified_at: tuple[int, Frames] | None = None  # frames buffered and the last one at the last try
        self._nis: deque[FloatArray] = deque(maxlen=s.noise_window)  # squared normalised innovations (3,) per frame
        self._nis_sum = np.zeros(3)
        self._normals: deque[FloatArray] = deque(maxlen=s.normals_kept)  # plane normals in the flange frame
        self._events: list[ChangeEvent] = []
        #: The estimate before the last classified change and its kind: its size is re-measured as the
        #: frames after it show more (the first fit after a change sees one or two poses only).
        self._before_change: tuple[FloatArray, str] | None = None
        self._seen_before: BoolArray | None = None  # parameters seen when the open change was detected
        self.frames_used = 0

    # ------------------------------------------------------------------ update
    def update(self, t_s: float, obs: PlaneObservation,
               systematic: Mapping[str, tuple[FloatArray, float]] | None = None) -> TrackStep:
        """Feed one frame's plane observation (``PlaneObservation`` with the flange pose at the frame time).

        ``systematic``: the fit's ``systematic_shifts`` (camera frame, per allowance term), for the intervals only.
        """
        s = self.settings
        if self._linear is None:
            self._linear = self._start(obs)
        frame = Frames.of(t_s, obs, s.arm_translation_sigma_m, s.arm_rotation_sigma_rad, self._lever,
                          self._slots(systematic))
        nu = self._innovation(frame)
        if float(nu @ nu) > s.detector_reference and self._since_batch and self._after is None:
            self._batch()  # a surprising frame: first relinearise every frame in the window, then judge it
            nu = self._innovation(frame)
        chi2 = float(nu @ nu)
        judged = chi2 / self._noise_scale2()  # against the noise the window has shown (>= the stated noise)
        self._recent.append((frame, judged))
        if self._after is not None:
            return self._while_changed(t_s, frame, nu, chi2)
        alarm = self._cusum.update(judged)
        if alarm:
            return self._detected(t_s, nu, chi2)
        if judged > s.detector_clip:  # far off the model: held back until the CUSUM decides
            return TrackStep(t_s, nu, chi2, False, note="residual far beyond the noise model")
        self._step(frame)
        self._remember_normal(obs)
        self._add_nis(nu * nu)
        event = self._check_resolved(t_s)
        return TrackStep(t_s, nu, chi2, True, event)

    def _slots(self, systematic: Mapping[str, tuple[FloatArray, float]] | None) -> FloatArray | None:
        """The shifts as (SYSTEMATIC_SLOTS, 4) in this tracker's slots (a term beyond the slots is left out)."""
        if not systematic:
            return None
        out = np.zeros((SYSTEMATIC_SLOTS, 4))
        for key, (normal, offset) in systematic.items():
            if key not in self._sys_keys:
                if len(self._sys_keys) == SYSTEMATIC_SLOTS:
                    continue
                self._sys_keys.append(key)
            k = self._sys_keys.index(key)
            out[k, :3] = np.asarray(normal, dtype=np.float64)
            out[k, 3] = float(offset)
        return out

    def _innovation(self, frame: Frames) -> FloatArray:
        """The frame's whitened residual at the estimate, normalised by its predicted covariance (3,)."""
        assert self._linear is not None
        r, jac = self._linear.linearise(self._x, frame)
        cov_pred = np.linalg.inv(self._info + self._weak * np.eye(9))  # the estimate's covariance with the prior
        innov_cov = np.eye(3) + jac[0] @ cov_pred @ jac[0].T  # predicted covariance of the whitened residual
        # the camera's systematic allowance: what of each term's shift at this frame the estimate has not taken
        # up (its differential part: the shift minus what the frames so far moved the estimate by) is no change
        bias = frame.systematic[0] - (self._sys_g @ cov_pred) @ jac[0].T  # (S, 3): b_k = δr_k - J H⁻¹ g_k
        innov_cov = innov_cov + bias.T @ bias
        nu: FloatArray = np.linalg.solve(np.linalg.cholesky(innov_cov), r[0])
        return nu

    def _start(self, obs: PlaneObservation) -> LinearModel:
        """The linear model with the configured plane turned toward the first frame's camera.

        The side is the measured normal's (toward the camera), seen in the base frame through the configured
        mount's rotation: not the camera's configured position, which is on the wrong side of a plane configured
        off by more than the camera's distance, and the residual (the normal's error across itself) cannot tell a
        normal from its opposite, so a wrong side would converge to the mirrored mount.
        """
        camera = obs.flange @ self.nominal_mount
        measured = camera.rotation_matrix @ np.asarray(obs.normal, dtype=np.float64)  # the measured normal, base frame
        if float(measured @ self.nominal_plane.normal) < 0:
            self.nominal_plane = Plane(-self.nominal_plane.normal, -self.nominal_plane.offset_m)
        return LinearModel(self.nominal_mount, self.nominal_plane)

    def _step(self, frame: Frames) -> None:
        """The iterated information-form update with one frame."""
        assert self._linear is not None
        x_prev, info_prev, parts_prev = self._x, self._info, self._parts
        x = x_prev.copy()
        jac = np.zeros((3, 9))
        for _ in range(self.settings.iterations):
            r, jac3 = self._linear.linearise(x, frame)  # relinearised about the current iterate
            jac = jac3[0]
            h = info_prev + self._weak * np.eye(9) + jac.T @ jac  # normal matrix
            g = info_prev @ (x - x_prev) + self._weak * x + jac.T @ r[0]  # gradient / 2
            x = x - np.linalg.solve(h, g)
        self._x = x
        self._info = info_prev + jac.T @ jac
        self._parts = parts_prev + _split(jac[None])
        self._sys_g = self._sys_g + frame.systematic[0] @ jac
        self.frames_used += 1
        self._keep(frame)
        self._since_batch += 1
        if self._since_batch >= self.settings.relinearise_every:
            self._batch()

    def _keep(self, frame: Frames) -> None:
        """Put an accepted frame in the window; the one it pushes out joins the prior, linearised at the estimate."""
        assert self._linear is not None
        old = self._window.push(frame)
        if old is not None:
            r, jac3 = self._linear.linearise(self._x, old)
            jac = jac3[0]
            self._prior_info += jac.T @ jac  # |r + J (x - x̂)|² = x'J'Jx - 2 x'J'(J x̂ - r) + const
            self._prior_parts += _split(jac3)
            self._prior_h += jac.T @ (jac @ self._x - r[0])
            self._prior_sys_g += old.systematic[0] @ jac

    def _batch(self) -> None:
        """Gauss-Newton over the window and the prior, every frame relinearised about the estimate."""
        assert self._linear is not None
        self._since_batch = 0
        if not len(self._window):
            self._info = self._prior_info.copy()
            self._parts = self._prior_parts.copy()
            self._sys_g = self._prior_sys_g.copy()
            return
        frames = self._window.frames()
        x = self._x
        j2 = np.zeros((0, 9))
        jac = np.zeros((0, 3, 9))
        for _ in range(self.settings.iterations):
            r, jac = self._linear.linearise(x, frames)
            j2 = jac.reshape(-1, 9)
            h = self._prior_info + self._weak * np.eye(9) + j2.T @ j2  # normal matrix
            g = self._prior_info @ x - self._prior_h + self._weak * x + j2.T @ r.ravel()  # gradient / 2
            x = x - np.linalg.solve(h, g)
        self._x = x
        self._info = self._prior_info + j2.T @ j2
        self._parts = self._prior_parts + _split(jac)
        self._sys_g = self._prior_sys_g + (np.einsum("nsk,nki->si", frames.systematic, jac)
                                           if len(jac) == len(frames) else 0.0)  # no iteration: no Jacobian
        if self._before_change is not None and self._events and self._after is None:
            old, kind = self._before_change  # the size of the last change, as the estimate now sees it
            self._events[-1] = replace(self._events[-1], size=self._size(old, x, kind))

    def _remember_normal(self, obs: PlaneObservation) -> None:
        """Keep the plane normal in the flange frame when it differs from the last kept one."""
        u = obs.flange.rotation_matrix.T @ self.nominal_plane.normal
        if not self._normals or math.acos(min(1.0, float(u @ self._normals[-1]))) > NORMAL_STEP_RAD:
            self._normals.append(u)

    def _noise_scale2(self) -> float:
        """The window's mean chi2 per residual, at least 1 and at most the largest interval scale squared.

        The change test divides each frame's chi2 by it, so that noise larger than stated (the
        intervals are scaled for it) is not taken for a change; a change is abrupt against it.
        """
        if len(self._nis) < MIN_NOISE_FRAMES:
            return 1.0
        worst = float(self._nis_sum.max()) / len(self._nis)  # the worst of the three residual components
        return min(max(1.0, worst), self.settings.max_interval_scale ** 2)

    def _add_nis(self, chi2: FloatArray) -> None:
        """Add a frame's squared normalised innovation (per component) to the noise test's window."""
        if len(self._nis) == self._nis.maxlen:
            self._nis_sum -= self._nis[0]
        self._nis.append(chi2)
        self._nis_sum += chi2

    # ------------------------------------------------------------------ changes
    def _detected(self, t_s: float, nu: FloatArray, chi2: float) -> TrackStep:
        """Open a change: back to the state before it, collect the frames after it."""
        # the frames after the change: the run's trailing frames beyond the clip when the alarm's frame is (a
        # large change: a frame before it that merely exceeded the reference stays out), else beyond the reference
        s = self.settings
        _, last = self._recent[-1]
        bound = s.detector_clip if last > s.detector_clip else s.detector_reference
        after: list[Frames] = []
        for frame, value in reversed(list(self._recent)[max(0, len(self._recent) - self._cusum.run_length):]):
            if value <= bound:
                break
            after.insert(0, frame)
        self._after = deque(after, maxlen=self.settings.change_window)
        self._classified_at = None
        self.frames_used -= self._window.drop_from(float(after[0].t_s[0]))  # frames after the change taken back
        self._batch()  # the state before the change
        self._seen_before = self._seen_mask(self._info)
        event = ChangeEvent(t_s, KIND_EITHER, {"innovation_chi2": chi2}, None, float(after[0].t_s[0]))
        self._events.append(event)
        self._cusum.reset()
        self._nis.clear()
        self._nis_sum = np.zeros(3)
        stepped = self._classify(t_s)
        return TrackStep(t_s, nu, chi2, stepped is not None, stepped or event, note="change detected")

    def _worth_classifying(self) -> bool:
        """Whether the frames since the last try can change the verdict: the arm moved, or enough came."""
        assert self._after is not None
        if self._classified_at is None or len(self._after) >= self.settings.change_window:
            return True
        count, last = self._classified_at
        new = self._after[-1]
        # the turn in rad: |R1 - R2|_F = 2 sqrt(2) sin(turn / 2), so the Frobenius norm over sqrt 2 is ~ the turn
        turned = float(np.linalg.norm(new.rot_a[0] - last.rot_a[0])) / math.sqrt(2.0)
        moved = float(np.linalg.norm(new.t_a[0] - last.t_a[0]))
        return turned > CLASSIFY_TURN_RAD or moved > CLASSIFY_MOVE_M or len(self._after) - count >= CLASSIFY_EVERY

    def _while_changed(self, t_s: float, frame: Frames, nu: FloatArray, chi2: float) -> TrackStep:
        """A frame after a detected change that is not classified yet."""
        assert self._after is not None
        self._after.append(frame)
        event = self._classify(t_s)
        return TrackStep(t_s, nu, chi2, event is not None, event,
                         note="" if event else "change not told apart yet: frames kept for the re-estimate")

    def _classify(self, t_s: float) -> ChangeEvent | None:
        """Try to tell the change apart and restart its block; the updated event when done."""
        assert self._after is not None and self._linear is not None
        s = self.settings
        if not self._worth_classifying():
            return None
        self._classified_at = (len(self._after), self._after[-1])
        frames = Frames.stack(list(self._after))
        kind, mount, plane = classify(self._linear, frames, self._x, self._info, self._weak, s.accept_level,
                                      s.reject_level)
        full = len(self._after) >= s.change_window
        if kind == KIND_EITHER and len(self._after) < s.min_change_frames:
            return None  # neither block alone fits a few frames: wait for more before restarting both
        if kind is None and not full:
            return None  # both fit: the poses since the change cannot tell them apart yet
        chosen = {KIND_MOUNT: mount, KIND_PLANE: plane}.get(kind or "")
        if chosen is None or kind is None:  # both blocks new: restart everything from the frames after the change
            from cellcal.core.track.detector import hypothesis

            chosen = hypothesis(KIND_EITHER, self._linear, frames, self._x, self._info, self._weak)
            kind = KIND_EITHER
        return self._restart(t_s, kind, chosen)

    def _restart(self, t_s: float, kind: str, chosen: Hypothesis) -> ChangeEvent:
        """Take the classified fit of the frames after the change as the new state."""
        from cellcal.core.track.detector import MOUNT, PLANE
        from cellcal.core.track.refit import marginal_info

        old_x = self._x
        kept = {KIND_MOUNT: PLANE, KIND_PLANE: MOUNT}.get(kind, np.array([], dtype=np.intp))
        held = marginal_info(self._info, kept, self._weak) if len(kept) else np.zeros((9, 9))
        self._x = chosen.fit.x
        self._prior_info = held  # the kept block's earlier information, about its earlier value
        self._prior_h = held @ old_x
        self._prior_parts = np.zeros((4, 9, 9))
        self._prior_parts[3] = held
        # the kept block carries the systematic shifts it had: as a prior of information `held` at its shifted value
        moved = self._sys_g @ np.linalg.inv(self._info + self._weak * np.eye(9))  # (S, 9) each term's shift
        self._prior_sys_g = moved @ held
        self._window.clear()
        assert self._after is not None
        for frame in self._after:  # the frames after the change only
            self._keep(frame)
        self._batch()
        self.frames_used += len(self._after)
        self._after = None
        self._recent.clear()
        event = replace(self._events[-1], kind=kind, size=self._size(old_x, self._x, kind))
        self._events[-1] = event
        self._before_change = (old_x, kind)
        resolved = self._check_resolved(t_s)
        return resolved or event

    def _size(self, old: FloatArray, new: FloatArray, kind: str) -> dict[str, float]:
        """How large the change was, in the units of the event."""
        assert self._linear is not None
        model = PlaneModel(self.nominal_mount, self.nominal_plane)
        out: dict[str, float] = {}
        if kind in (KIND_MOUNT, KIND_EITHER):
            a, b = model.mount(old), model.mount(new)
            out["rotation_deg"] = math.degrees(a.angle_to(b))
            out["translation_m"] = a.distance_to(b)
        if kind in (KIND_PLANE, KIND_EITHER):
            p, q = model.plane(old), model.plane(new)
            out["plane_tilt_deg"] = math.degrees(math.acos(min(1.0, float(p.normal @ q.normal))))
            out["plane_offset_m"] = float(q.offset_m - p.offset_m)  # of n.x + offset = 0
            out["plane_shift_m"] = float(p.offset_m - q.offset_m)  # moved along its normal, toward the camera
        if self.fixed:  # what a fixed camera's one view measures: the plane in its own frame
            a_view, b_view = self.view_plane(old), self.view_plane(new)
            out["view_tilt_deg"] = math.degrees(math.acos(min(1.0, float(a_view.normal @ b_view.normal))))
            out["view_shift_m"] = float(a_view.offset_m - b_view.offset_m)  # toward the camera
        return out

    def view_plane(self, x: FloatArray | None = None) -> Plane:
        """The plane in the camera's frame at parameters ``x`` (default: the estimate), normal toward the camera.

        For a camera on the flange this is the view at the identity flange pose; for a fixed camera
        (``fixed``) it is its view, whatever part of it the pose or the plane takes (they trade fully).
        """
        model = PlaneModel(self.nominal_mount, self.nominal_plane)
        step = self._x if x is None else x
        seen = model.plane(step).transformed(model.mount(step).inv())
        return seen if seen.offset_m > 0 else Plane(-seen.normal, -seen.offset_m)

    def _check_resolved(self, t_s: float) -> ChangeEvent | None:
        """Mark the open change resolved once every parameter seen before it is seen again; the event if so."""
        if not self._events or self._events[-1].resolved_at_s is not None or self._after is not None:
            return None
        assert self._seen_before is not None
        if np.any(self._seen_before & ~self._seen_mask(self._info)):
            return None
        event = replace(self._events[-1], resolved_at_s=t_s)
        self._events[-1] = event
        return event

    # ------------------------------------------------------------------ state
    def _unseen_basis(self, info: FloatArray) -> FloatArray:
        """Orthonormal directions (columns, 9 x k) whose 1-sigma exceeds the hand-eye threshold."""
        lam, vec = np.linalg.eigh(info)
        threshold = max(UNOBSERVABLE_SIGMA ** -2, float(lam[-1]) * 1e-20)  # as observability.analyse (squared)
        out: FloatArray = vec[:, lam < threshold]
        return out

    def _seen_mask(self, info: FloatArray) -> BoolArray:
        """Per parameter, whether it lies (nearly) outside the unseen subspace."""
        null = self._unseen_basis(info)
        mask: BoolArray = np.linalg.norm(null, axis=1) < SEEN_SHARE
        return mask

    @property
    def state(self) -> TrackState:
        """The current estimate with intervals for what the work has shown."""
        from cellcal.core.handeye.estimator import rpy_with_sigma_deg

        s = self.settings
        model = PlaneModel(self.nominal_mount, self.nominal_plane)
        null = self._unseen_basis(self._info)
        x = self._x - null @ (null.T @ self._x)  # the configured values along what is unseen
        seen = np.linalg.norm(null, axis=1) < SEEN_SHARE
        # the stated noise tested per residual component (normal across x2, offset), both ways; a
        # component with more residual than stated has its information's share of the covariance
        # scaled by its chi2/dof (a sandwich: never narrower than the data support)
        checks = [check_noise(float(v), len(self._nis), confidence=s.confidence, level=s.noise_test_level,
                              max_interval_scale=math.inf) for v in self._nis_sum] if self._nis else []
        factors = np.array([c.interval_scale**2 for c in checks] + [1.0]) if checks else np.ones(4)
        noise = max(checks, key=lambda c: c.chi2) if checks else None  # the worst component's test
        scale = float(np.sqrt(factors.max()))
        z = noise.interval_z if noise else _normal_z(s.confidence)
        withheld = ""
        if scale > s.max_interval_scale:
            withheld = (f"the residuals are {scale:.1f}x the stated noise: the noise model or the configured "
                        "values are wrong, intervals withheld")
        lam, vec = np.linalg.eigh(self._info)
        keep = lam >= max(UNOBSERVABLE_SIGMA ** -2, float(lam[-1]) * 1e-20)
        inv = (vec[:, keep] / lam[keep]) @ vec[:, keep].T  # pseudo-inverse on the seen subspace
        cov = inv @ np.einsum("k,kij->ij", factors, self._parts) @ inv  # the sandwich with the measured noise
        cov = cov + self._common_covariance(inv, seen)  # what does not change from frame to frame: never scaled
        cov[~seen, :] = np.nan
        cov[:, ~seen] = np.nan
        if withheld or self._after is not None:
            cov = np.full((9, 9), np.nan)
        mount = model.mount(x)
        rot_cov = np.nan_to_num(cov[MOUNT_ROTATION, MOUNT_ROTATION])
        _, rpy_sigma = rpy_with_sigma_deg(mount, rot_cov)
        _, rpy_unseen = rpy_with_sigma_deg(mount, null[MOUNT_ROTATION] @ null[MOUNT_ROTATION].T)  # share of the unseen
        rpy_sigma[rpy_unseen > math.degrees(SEEN_SHARE)] = np.nan  # an angle that moves with an unseen turn
        if not np.isfinite(cov[MOUNT_ROTATION, MOUNT_ROTATION]).any():
            rpy_sigma[:] = np.nan  # intervals withheld, or no turn seen
        observable = {name: bool(seen[i]) for i, name in enumerate(PARAMETERS)}
        sq = np.sqrt(np.abs(np.diag(cov)))
        return TrackState(
            mount, model.plane(x), sq[MOUNT_TRANSLATION].copy(), rpy_sigma, np.degrees(sq[PLANE_TILT]),
            float(sq[PLANE_OFFSET]), observable, self._unseen_texts(), self.frames_used, list(self._events),
            any(e.resolved_at_s is None for e in self._events), z, scale, noise, x, cov, s.confidence, withheld,
            self._interval_notes())

    def _interval_notes(self) -> tuple[str, ...]:
        """What the reported covariance carries besides the noise, in words."""
        notes = []
        if self._sys_keys:
            notes.append(f"the camera's systematic allowance ({', '.join(self._sys_keys)}) is common to the frames: "
                         "its shift of the estimate is in the intervals, not in the frames' weights")
        accuracy = self.settings.arm_accuracy
        if accuracy is not None and (accuracy.position_m or accuracy.rotation_rad):
            notes.append(f"the arm's absolute accuracy ({1000 * accuracy.position_m:.3g} mm, "
                         f"{math.degrees(accuracy.rotation_rad):.3g} deg RMS, stated by {accuracy.source}) is in the "
                         "intervals as an error common to the frames (mount and plane), not in the weights")
        return tuple(notes)

    def _common_covariance(self, inv: FloatArray, seen: BoolArray) -> FloatArray:
        """The covariance of the errors common to the frames: the camera's systematic allowance and the arm's accuracy.

        Each allowance term's coefficient is common to every frame: it moves the estimate by ``Λ⁺ Σ Jᵀ δr``
        (rows of ``_sys_g``); the arm's error common to the frames is a mount and a plane error
        (:meth:`~cellcal.core.handeye.estimator.ArmAccuracy.common_covariance`). Neither is in the weights.
        """
        shifts = self._sys_g @ inv  # (S, 9): each term's 1-sigma shift of the parameters (inv is symmetric)
        cov: FloatArray = shifts.T @ shifts
        accuracy = self.settings.arm_accuracy
        if accuracy is not None and (accuracy.position_m or accuracy.rotation_rad):
            cov = cov + accuracy.common_covariance(self.nominal_mount, np.flatnonzero(seen).tolist())
        return cov

    def _unseen_texts(self) -> list[str]:
        """What the work has not shown, named as the hand-eye observability report names it."""
        if not self._normals:
            return ["nothing yet: no frame has been used"]
        lam, vec = np.linalg.eigh(self._info)
        root = np.sqrt(np.clip(lam, 0.0, None))[:, None] * vec.T  # a square root of the information
        report = analyse(root, list(range(9)), np.array(self._normals))
        return [f"{d.what}: not shown by the work so far (would need {d.fix})" for d in report.unseen]


def _split(jac: FloatArray) -> FloatArray:
    """Information ``JᵀJ`` of stacked Jacobians (N, 3, 9) split by residual component, plus an empty 4th (4, 9, 9)."""
    out = np.zeros((4, 9, 9))
    out[:3] = np.einsum("nki,nkj->kij", jac, jac)
    return out


def _normal_z(confidence: float) -> float:
    """Half-width of a two-sided normal interval, in sigmas."""
    from cellcal.core.handeye.noise import normal_z

    return float(normal_z(confidence))


__all__ = ["Tracker"]
