"""fit_depthcal with ``estimate_mount``: what a depth-calibration plan can and cannot tell about the mount.

The plan of the depth calibration turns the camera about the plane's normal and tilts it by up to 20 deg: the
mount's rotation is seen through the plane's tilt in each view, the mount's translation across the plane only
through the small tilts, confounded with the plane and the image field. The fit must say so (observability) and
the correction must stay inside its intervals with the mount free; ``cellcal depthcal`` keeps the mount fixed
(docs/commands/depthcal.md, "The mount").
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from cellcal.core.depthcal import DepthcalResult, fit_depthcal
from cellcal.devices.pose import Pose
from tests.support.depthcal_views import MOUNT, bow_error, plan, stereo_views

#: The stereo truth of test_depthcal_fit: f·B 0.8 % too large, 0.15 px offset, a 0.6 px radial bow at the corner.
TRUTH = bow_error("stereo", 0.6, 320, 200, fb_error=0.008, disparity_offset_px=0.15)
#: The configured mount is off the true one by 2-3 mm and 0.2-0.5 deg.
OFF = Pose.from_xyz_rpy([0.002, -0.0015, 0.003], np.radians([0.3, -0.2, 0.5]))


@pytest.fixture(scope="module")
def fit() -> DepthcalResult:
    views, _ = stereo_views(TRUTH, plan(seed=1), seed=1, width=320, height=200)
    return fit_depthcal(views, mount=MOUNT @ OFF, model=views[0].frame.measurement, seed=1, estimate_mount=True)


def test_the_mount_s_rotation_is_recovered_within_its_intervals(fit: DepthcalResult) -> None:
    assert fit.mount is not None and fit.mount_covariance is not None
    err = (MOUNT.inv() @ fit.mount).as_xyz_rotvec()[3:]                       # rad, in the mount's frame
    sigma = np.sqrt(np.diag(fit.mount_covariance))[:3]
    # measured: errors 0.002-0.025 deg against 1-sigmas of 0.017-0.025 deg (started 0.2-0.5 deg off)
    assert np.all(sigma < math.radians(0.05))
    assert np.all(np.abs(err) <= 3.0 * sigma)
    assert math.degrees(float(np.linalg.norm(err))) < 0.1


def test_the_mount_s_translation_across_the_plane_is_said_to_be_unseen(fit: DepthcalResult) -> None:
    # measured: mount_tx_m 1-sigma 0.16 m (the 10 mm limit), confounded with mount_ty_m (correlation -0.97)
    assert not fit.observability.observable
    assert "mount_tx_m" in fit.observability.message()
    assert any("not seen by this plan" in note and "mount_t" in note for note in fit.notes)
    assert fit.mount_covariance is not None
    assert math.sqrt(fit.mount_covariance[3, 3]) > 0.01


def test_the_correction_stays_inside_its_intervals_with_the_mount_free(fit: DepthcalResult) -> None:
    c = fit.correction
    true = dict(zip(TRUTH.names, TRUTH.vector, strict=True))
    z = [(v - true.get(n, 0.0)) / s for n, v, s in zip(c.names, c.vector, c.leftover_sigma(c.names), strict=True)
         if s > 0]
    # measured |z| <= 1.5 over the 7 terms (scale, offset, the order-2 field)
    assert len(z) >= 2 and max(abs(v) for v in z) < 3.5
