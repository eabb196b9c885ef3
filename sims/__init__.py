"""cellcal.sims: the simulated cell (scene, O3R222-like camera, xArm-5-like arm) and emulators.

Import the submodules you need (``cellcal.sims.camera``, ``cellcal.sims.arm``,
``cellcal.sims.world``, ``cellcal.sims.scene``); this package module imports nothing
heavy itself. The ``sim`` backends are registered through entry points pointing at
``cellcal.sims.backends``.
"""
