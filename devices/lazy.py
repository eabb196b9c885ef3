"""Lazy re-exports of a package's public names (PEP 562), so that importing it stays cheap (ADR 0021)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping
from importlib import import_module
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package`` for names defined in its submodules.

    Args:
        package: The package's ``__name__``.
        exports: Public name -> the module defining it (absolute, or relative to ``package``).

    Returns:
        ``(__getattr__, __dir__)``: the first imports a name's module on first use and keeps
        the value in the package (later lookups do not come back), or raises AttributeError.
    """

    def module_getattr(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(import_module(module, package), name)
        setattr(sys.modules[package], name, value)  # later lookups skip this function
        return value

    def module_dir() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return module_getattr, module_dir
