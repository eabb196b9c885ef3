"""cellcal backend for the ACME Z1 time-of-flight camera (an example vendor package).

Importing this package imports no backend: cellcal finds them through the
``cellcal.cameras`` entry points and loads :mod:`acme_cellcal.camera` (``acme-z1``) or
:mod:`acme_cellcal.emulated` (``acme-z1-emulated``) only when a configuration uses them.
"""

__version__ = "0.1.0"
