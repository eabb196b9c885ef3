"""cellcal.core: math and orchestration (geometry, camera model, plane fits, the paper's methods, calibrator, reports, CLI). No device I/O."""
