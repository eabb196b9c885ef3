"""cellcal.core: math and orchestration.

Geometry, the camera model, plane fits, the paper's methods, the calibrator, reports
and the CLI. No device I/O: devices come from the registry in :mod:`cellcal.devices`.
"""
