"""cellcal.sims: the simulated cell (scene, O3R222-like camera, xArm-5-like arm) and wire-level emulators.

Imports nothing itself: the ``sim`` backends are ``cellcal.sims.camera.SimCamera`` and ``cellcal.sims.arm.SimArm``
(entry points ``cameras: sim``, ``arms: sim``); the emulators are ``cellcal.sims.o3r`` and ``cellcal.sims.xarm``.
"""
