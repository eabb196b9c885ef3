"""The vectorised plane model agrees with the hand-eye model and its Jacobian."""

from __future__ import annotations

import numpy as np

from cellcal.core.handeye.estimator import jacobian
from cellcal.core.handeye.model import PlaneModel
from cellcal.core.handeye.synthetic import observations, sim_scenario
from cellcal.core.track.linear import Frames, LinearModel, rotvec_matrices


def test_rodrigues_matches_scipy() -> None:
    from scipy.spatial.transform import Rotation

    v = np.array([[0.0, 0.0, 0.0], [1e-9, 0.0, 0.0], [0.3, -1.2, 0.5], [0.0, 3.0, 0.0]])
    np.testing.assert_allclose(rotvec_matrices(v), Rotation.from_rotvec(v).as_matrix(), atol=1e-14)


def test_residuals_and_jacobian_match_the_handeye_model() -> None:
    sc = sim_scenario()
    obs = observations(sc, np.random.default_rng(3))
    model = LinearModel(sc.nominal_mount, sc.nominal_plane)
    frames = Frames.stack([Frames.of(float(k), o, 2.5e-5, 1e-4, 0.07) for k, o in enumerate(obs)])
    x = np.array([0.01, -0.008, 0.012, 0.003, -0.004, 0.003, 2e-4, -3e-4, 0.0012])
    r, jac = model.linearise(x, frames)
    normals, offsets = PlaneModel(sc.nominal_mount, sc.nominal_plane).predict(x, [o.flange for o in obs])
    raw = np.column_stack([np.einsum("nij,ni->nj", frames.bases, normals - frames.normals), offsets - frames.offsets])
    np.testing.assert_allclose(r, np.einsum("nij,nj->ni", frames.whiten, raw), rtol=1e-9, atol=1e-9)

    def flat(p: np.ndarray) -> np.ndarray:
        return model.residuals(p[None], frames)[0].ravel()

    np.testing.assert_allclose(jac.reshape(-1, 9), jacobian(flat, x), rtol=1e-6, atol=1e-3)
    assert np.abs(jac).max() > 1e3  # per rad / per m of whitened residual: far from zero
