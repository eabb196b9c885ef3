"""cellcal backend for the ACME Z1 time-of-flight camera (an example vendor package).

Importing this package imports neither the camera class nor the (stand-in) SDK:
cellcal finds the backend through the ``cellcal.cameras`` entry point and loads
:mod:`acme_cellcal.camera` only when a configuration uses ``backend = "acme-z1"``.
"""

__version__ = "0.1.0"
