"""Backend registry: names -> device classes, from entry points or explicit registration.

Backends are found through the entry-point groups ``cellcal.cameras`` and
``cellcal.arms`` (ADR 0005), e.g. in a vendor's ``pyproject.toml``::

    [project.entry-points."cellcal.cameras"]
    acme = "acme_cellcal.camera:AcmeCamera"
"""

from __future__ import annotations

import importlib.metadata as md
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

from .arm import RobotArm
from .base import BackendContext, Device
from .camera import Camera3D
from .errors import ConfigError, RegistryError

Kind = Literal["camera", "arm"]
GROUPS: dict[Kind, str] = {"camera": "cellcal.cameras", "arm": "cellcal.arms"}
_BASES: dict[Kind, type[Device]] = {"camera": Camera3D, "arm": RobotArm}  # type: ignore[type-abstract]


@dataclass(frozen=True)
class BackendEntry:
    """One registered backend.

    Attributes:
        kind: ``"camera"`` or ``"arm"``.
        name: Name used in configs (``backend = "..."``).
        target: ``"module:Class"`` it loads from.
        source: Where it comes from: ``"runtime"`` (or another label), or the
            ``importlib.metadata`` distribution that declares it — read only when
            :attr:`origin` is asked for (parsing every distribution's metadata at start-up
            would cost every command tens of milliseconds).
    """

    kind: Kind
    name: str
    target: str
    source: Any = field(default="runtime", compare=False)

    @property
    def origin(self) -> str:
        """The distribution name and version, ``"unknown distribution"``, or the given label."""
        if isinstance(self.source, str):
            return self.source
        if self.source is None:
            return "unknown distribution"
        return f"{self.source.name} {self.source.version}"


class Registry:
    """Maps backend names to device classes for cameras and arms.

    Entry points are only *listed* at start-up; a backend's module (and through it the
    vendor SDK) is imported when the backend is first used. Two distributions claiming
    one name is a :class:`RegistryError`, never a silent pick.
    """

    def __init__(self, *, discover: bool = True):
        self._entries: dict[tuple[Kind, str], BackendEntry] = {}
        self._loaded: dict[tuple[Kind, str], type[Device]] = {}
        self._lock = threading.Lock()
        self._discovered = not discover

    # ------------------------------------------------------------ registration
    def register(self, kind: Kind, name: str, cls: type[Device], *, origin: str = "runtime") -> None:
        """Register a device class under ``name`` at run time.

        Raises:
            RegistryError: If the name is taken, or ``cls`` is not a subclass of the interface.
        """
        self._discover()
        base = _BASES[kind]
        if not (isinstance(cls, type) and issubclass(cls, base)):
            raise RegistryError(f"{kind} backend '{name}' must subclass {base.__name__}, got {cls!r}")
        with self._lock:
            key = (kind, name)
            if key in self._entries:
                raise RegistryError(
                    f"duplicate {kind} backend '{name}': already registered by {self._entries[key].origin}"
                )
            self._entries[key] = BackendEntry(kind, name, f"{cls.__module__}:{cls.__qualname__}", origin)
            self._loaded[key] = cls

    def unregister(self, kind: Kind, name: str) -> None:
        """Remove a backend (mainly for tests)."""
        with self._lock:
            self._entries.pop((kind, name), None)
            self._loaded.pop((kind, name), None)

    def _discover(self) -> None:
        if self._discovered:
            return
        with self._lock:
            if self._discovered:
                return
            found: dict[tuple[Kind, str], BackendEntry] = {}
            for kind, group in GROUPS.items():
                for ep in md.entry_points(group=group):
                    key = (kind, ep.name)
                    entry = BackendEntry(kind, ep.name, ep.value, getattr(ep, "dist", None))
                    if key in found and found[key].target != ep.value:
                        raise RegistryError(
                            f"duplicate {kind} backend '{ep.name}': provided by {found[key].origin} "
                            f"({found[key].target}) and by {entry.origin} ({ep.value})"
                        )
                    found[key] = entry
            self._entries.update(found)
            self._discovered = True

    # ------------------------------------------------------------ lookup
    def entries(self, kind: Kind | None = None) -> list[BackendEntry]:
        """All registered backends, sorted by kind then name."""
        self._discover()
        return sorted((e for e in self._entries.values() if kind is None or e.kind == kind),
                      key=lambda e: (e.kind, e.name))

    def names(self, kind: Kind) -> list[str]:
        """Registered backend names of one kind."""
        return [e.name for e in self.entries(kind)]

    def get(self, kind: Kind, name: str) -> type[Device]:
        """The device class registered as ``name``, importing its module if needed.

        Raises:
            RegistryError: If no such backend exists or its module fails to import.
        """
        self._discover()
        key = (kind, name)
        with self._lock:
            if key in self._loaded:
                return self._loaded[key]
            entry = self._entries.get(key)
        if entry is None:
            known = ", ".join(self.names(kind)) or "(none)"
            raise RegistryError(f"unknown {kind} backend '{name}'; registered: {known}")
        module_name, _, attr = entry.target.partition(":")
        try:
            obj: Any = importlib_import(module_name)
            for part in attr.split("."):
                obj = getattr(obj, part)
        except ImportError as exc:
            raise RegistryError(f"{kind} backend '{name}' ({entry.target}) failed to import: {exc}") from exc
        except AttributeError as exc:
            raise RegistryError(f"{kind} backend '{name}': {entry.target} not found") from exc
        base = _BASES[kind]
        if not (isinstance(obj, type) and issubclass(obj, base)):
            raise RegistryError(f"{kind} backend '{name}' ({entry.target}) is not a {base.__name__}")
        with self._lock:
            self._loaded[key] = obj
        return obj

    def create(self, kind: Kind, section: Mapping[str, Any], context: BackendContext | None = None, *,
               apply_correction: bool = True) -> Device:
        """Build an unconnected device from a config section holding ``backend = "name"``.

        A camera section's ``correction`` table (``[camera.correction] file = ...``) is read here and
        the camera wrapped in :class:`~cellcal.devices.correction.CorrectedCamera`, so that every
        command corrects every frame (ADR 0058); ``apply_correction=False`` checks the table but
        returns the raw camera (``cellcal depthcal``).

        Raises:
            ConfigError: If ``backend`` is missing or names no registered backend, or the
                backend rejects its section, or the correction table or its file is bad.
        """
        context = context or BackendContext(section=kind)
        name = section.get("backend")
        if not isinstance(name, str):
            raise ConfigError(f"missing 'backend' (a string; one of: {', '.join(self.names(kind))})",
                              source=context.source, key=f"{context.section}.backend")
        try:
            cls = self.get(kind, name)
        except RegistryError as exc:
            raise ConfigError(str(exc), source=context.source, key=f"{context.section}.backend") from None
        if kind == "camera" and "correction" in section:
            from .correction import camera_with_correction  # numpy's arithmetic, only for a corrected camera

            rest = {k: v for k, v in section.items() if k != "correction"}
            camera = cls.from_config(rest, context)
            assert isinstance(camera, Camera3D)
            return camera_with_correction(camera, section["correction"], context, apply=apply_correction)
        return cls.from_config(section, context)

    def create_camera(self, section: Mapping[str, Any], context: BackendContext | None = None, *,
                      apply_correction: bool = True) -> Camera3D:
        """:meth:`create` for cameras, typed (``apply_correction``: see :meth:`create`)."""
        dev = self.create("camera", section, context, apply_correction=apply_correction)
        assert isinstance(dev, Camera3D)
        return dev

    def create_arm(self, section: Mapping[str, Any], context: BackendContext | None = None) -> RobotArm:
        """:meth:`create` for arms, typed."""
        dev = self.create("arm", section, context)
        assert isinstance(dev, RobotArm)
        return dev


def importlib_import(module_name: str) -> Any:
    """Import a module by name (a seam for tests)."""
    import importlib

    return importlib.import_module(module_name)


_default: Registry | None = None


def default_registry() -> Registry:
    """The process-wide registry, discovering entry points on first use."""
    global _default
    if _default is None:
        _default = Registry()
    return _default
