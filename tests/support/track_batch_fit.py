"""An independent least-squares fit of the tracker's frames, for the pinned tracker tests.

The whitened residuals come from the hand-eye model (``PlaneModel.predict`` and ``whitening``, not
:mod:`cellcal.core.track.linear`), are minimised with ``scipy.optimize.least_squares`` and give the covariance
from its Jacobian; ``rpy`` sigmas from finite differences of ``Pose.as_xyz_rpy``. ``feed`` runs a tracker over
synthetic work of the simulator's scenario ``SC`` (arm noise ``ARM_SIGMA_M`` m, lever ``LEVER_M`` m, the weak
prior's information ``WEAK``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy.optimize import least_squares

from cellcal.core.geometry.planes import Plane
from cellcal.core.handeye.model import PlaneModel, PlaneObservation, whitening
from cellcal.core.handeye.synthetic import Scenario, sim_scenario
from cellcal.core.track import Tracker
from cellcal.core.track.synthetic import work
from cellcal.devices.pose import Pose

SC = sim_scenario()
ARM_SIGMA_M = 2.5e-5
LEVER_M = float(np.linalg.norm(SC.nominal_mount.translation))
WEAK = 0.05 ** -2


def feed(tracker: Tracker, scenario: Scenario, seed: int, frames: int, dwell: int = 10, start: int = 0
         ) -> list[tuple[PlaneObservation, object]]:
    """Run the tracker over synthetic work; (observation, step) per frame."""
    out = []
    for t_s, obs in work(scenario, np.random.default_rng(seed), frames, dwell=dwell, start_frame=start):
        out.append((obs, tracker.update(t_s, obs)))
    return out


def residuals_of(obs: list[PlaneObservation], plane: Plane = SC.nominal_plane, rotation_sigma_rad: float = 0.0
                 ) -> Callable[[np.ndarray], np.ndarray]:
    """The whitened residuals (N, 3) of the frames as a function of the nine parameters, from the hand-eye model.

    The predicted normal's error across the measured one (2) and the offset's, whitened by ``whitening`` of
    each observation (the arm's turn noise acting through the configured mount's lever).
    """
    model = PlaneModel(SC.nominal_mount, plane)
    flanges = [o.flange for o in obs]
    pairs = [whitening(o, ARM_SIGMA_M, rotation_sigma_rad, LEVER_M) for o in obs]
    bases, whites = np.array([b for b, _ in pairs]), np.array([w for _, w in pairs])
    normals = np.array([o.normal for o in obs])
    offsets = np.array([o.offset_m for o in obs])

    def fun(x: np.ndarray) -> np.ndarray:
        n, c = model.predict(x, flanges)
        raw = np.concatenate([np.einsum("nij,ni->nj", bases, n - normals), (c - offsets)[:, None]], axis=1)
        return np.einsum("nij,nj->ni", whites, raw)

    return fun


def batch(obs: list[PlaneObservation], plane: Plane = SC.nominal_plane, rotation_sigma_rad: float = 0.0
          ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares fit of all frames with the weak prior: the parameters and the Jacobian (N, 3, 9) at them."""
    fun = residuals_of(obs, plane, rotation_sigma_rad)
    root = math.sqrt(WEAK)
    sol = least_squares(lambda x: np.r_[fun(x).ravel(), root * x], np.zeros(9), xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, x_scale=1e-3)
    return sol.x, sol.jac[:-9].reshape(len(obs), 3, 9)


def rpy_sigma_deg(mount: Pose, cov_rot: np.ndarray) -> np.ndarray:
    """1-sigma of rpy_deg by finite differences of ``Pose.as_xyz_rpy`` over turns about the flange axes."""
    from scipy.spatial.transform import Rotation

    h = 1e-7
    cols = []
    for e in np.eye(3):
        plus = Pose(Rotation.from_rotvec(h * e) * mount.rotation, mount.translation).as_xyz_rpy()[3:]
        minus = Pose(Rotation.from_rotvec(-h * e) * mount.rotation, mount.translation).as_xyz_rpy()[3:]
        cols.append((plus - minus) / (2 * h))
    g = np.column_stack(cols)
    return np.degrees(np.sqrt(np.diag(g @ cov_rot @ g.T)))
