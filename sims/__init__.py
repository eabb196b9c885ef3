"""cellcal.sims: the simulated cell (scene, O3R222-like camera, xArm-5-like arm) and emulators.

Import the submodules you need (``cellcal.sims.camera``, ``cellcal.sims.arm``,
``cellcal.sims.world``, ``cellcal.sims.scene``); this package module imports nothing
heavy itself. The ``sim`` backends are :class:`cellcal.sims.camera.SimCamera` and
:class:`cellcal.sims.arm.SimArm` (entry points ``cameras: sim`` and ``arms: sim``).
"""
