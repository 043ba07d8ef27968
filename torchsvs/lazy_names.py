"""A package's public names imported on first use (PEP 562): what ``torchsvs``,
``torchsvs.datasets`` and ``torchsvs.training`` share, so that importing one light part (reading
a file: numpy and Arrow; a training config) does not import torch or Lightning."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(
    package: str, homes: Mapping[str, str | None], namespace: dict[str, Any]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The package's ``__getattr__`` and ``__dir__``: ``homes`` maps each public name to the
    module it lives in (absolute, ``torchsvs.…``, or a submodule of ``package``; ``None``: the
    name is a subpackage), ``namespace`` is the package's ``globals()``, where a name resolved
    once is kept (found directly from then on)."""

    def getattr_(name: str) -> Any:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        home = homes[name]
        if home is None:
            value: Any = importlib.import_module(f"{package}.{name}")
        else:
            module = home if home.startswith("torchsvs.") else f"{package}.{home}"
            value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def dir_() -> list[str]:
        return sorted({*namespace, *homes})

    return getattr_, dir_
