"""The source registry: every kind of device or file bodynet takes samples from.

Like python-can's interface table, the registry maps a source's name to the
class that implements it, as ``"module:Class"``, imported only when that source
is used. The command line builds ``bridge``, ``emulate``, ``node``, ``decode``
and ``process`` from it, so adding a source is one module (a subclass of
:class:`~bodynet.nodes.sources.base.Source`) and one line here, or one call of
:func:`register` from code that adds it at run time.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from bodynet.nodes.sources.base import Source

#: source name -> "module:Class"; the name is the one ``bodynet bridge`` takes.
REGISTRY: dict[str, str] = {
    "can": "bodynet.nodes.sources.smartsuit_can:SmartSuitCan",
    "concentrator": "bodynet.nodes.sources.concentrator:Concentrator",
    "imu-central": "bodynet.nodes.sources.imu_central:ImuCentral",
    "slimevr": "bodynet.nodes.sources.slimevr:SlimeVR",
    "orientation-file": "bodynet.nodes.sources.orientation_files:OrientationFile",
}

_loaded: dict[str, type[Source]] = {}


class UnknownSource(KeyError):
    """No source of that name (or capture format, or emulated device)."""

    def __str__(self) -> str:
        return str(self.args[0])


def register(name: str, target: str | type[Source]) -> None:
    """Add (or replace) a source: ``target`` is its class or ``"module:Class"``."""
    _loaded.pop(name, None)
    if isinstance(target, str):
        REGISTRY[name] = target
    else:
        REGISTRY[name] = f"{target.__module__}:{target.__qualname__}"
        _loaded[name] = target


def unregister(name: str) -> None:
    REGISTRY.pop(name, None)
    _loaded.pop(name, None)


def get(name: str) -> type[Source]:
    """The source class registered as ``name``, imported on first use."""
    cls = _loaded.get(name)
    if cls is not None:
        return cls
    try:
        target = REGISTRY[name]
    except KeyError:
        raise UnknownSource(f"no source {name!r}; sources: {', '.join(sorted(REGISTRY))}") from None
    module, _, attr = target.partition(":")
    cls = getattr(importlib.import_module(module), attr)
    _loaded[name] = cls
    return cls


def names() -> list[str]:
    return list(REGISTRY)


def all_sources() -> list[type[Source]]:
    return [get(name) for name in REGISTRY]


def formats() -> dict[str, type[Source]]:
    """Capture format (``bodynet decode --format``) -> the source that reads it."""
    return {fmt: cls for cls in all_sources() for fmt in cls.formats}


def _one(table: dict[str, type[Source]], key: str, what: str) -> type[Source]:
    try:
        return table[key]
    except KeyError:
        raise UnknownSource(f"no {what} {key!r}; {what}s: {', '.join(sorted(table))}") from None


def by_format(fmt: str) -> type[Source]:
    return _one(formats(), fmt, "capture format")


def emulated_devices() -> dict[str, type[Source]]:
    """Emulated device (``bodynet emulate DEVICE``, ``node --via``) -> its source."""
    return {dev: cls for cls in all_sources() for dev in cls.emulators}


def by_device(device: str) -> type[Source]:
    return _one(emulated_devices(), device, "emulated device")
