"""Native vendor libraries in a worker process, so their crash is an error and not the end of cellcal.

A backend that wraps native code declares ``wraps_native_code = True`` and reaches the
library through a :class:`NativeHost`: modules imported, objects built and methods called in
a child process over a pipe, each call bounded by a deadline. A segfault or an abort in the
library ends the child only; the caller gets :class:`~cellcal.devices.errors.NativeCrashError`.
:class:`InlineHost` offers the same interface in-process (debugging, mocked unit tests).
Design: docs/adr/0038-native-isolation.md.
"""

from __future__ import annotations

from .host import NativeHost, RemoteModule, RemoteObject
from .inline import InlineHost

__all__ = ["InlineHost", "NativeHost", "RemoteModule", "RemoteObject"]
