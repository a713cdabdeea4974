"""Which command needs which optional extra: the one place that knows, checked before any work.

Every ``dmarionette`` command calls :func:`check_command_extras` with its parsed arguments before
it reads, simulates or writes anything (``dmarionette.cli.main`` does it for built-in and plug-in
commands alike). A missing package is one line naming the extra to install, exit code 2::

    error: 'dmarionette info' needs the mcap package: pip install -e '.[io]'

The check looks a module up (``importlib.util.find_spec``) without importing it, so it costs
microseconds, and a module made unimportable (``sys.modules[name] = None``, an import blocker)
counts as missing.
"""

from __future__ import annotations

import argparse
import importlib.util
from collections.abc import Iterable

__all__ = ["EXTRAS", "MissingExtraError", "check_extras", "check_command_extras", "command_extras",
           "missing_module"]

EXTRAS: dict[str, tuple[tuple[str, str], ...]] = {
    # extra: (module to look up, the package that brings it), as in pyproject.toml's optional-dependencies
    "io": (("mcap", "mcap"),),
    "viz": (("matplotlib", "matplotlib"), ("imageio", "imageio"), ("PIL", "pillow")),
    "mp4": (("imageio_ffmpeg", "imageio-ffmpeg"),),
    "view": (("viser", "viser"),),
    "fitting": (("jax", "jax"), ("optimistix", "optimistix"), ("tomli_w", "tomli-w"), ("mcap", "mcap")),
    "hw-falcon": (("usb", "pyusb"),),
    "hw-spacemouse": (("hid", "hidapi"),),
    "usd": (("pxr", "usd-core"),),
    "scale": (("ray", "ray"),),
}
"""Extra -> the modules it brings, each with its package's name. ``hw-*`` are the ``hw`` extra's parts."""

_PIP_EXTRA = {"hw-falcon": "hw", "hw-spacemouse": "hw"}


class MissingExtraError(RuntimeError):
    """A command needs a package that is not installed; the message names the extra to install."""


def missing_module(module: str) -> bool:
    """Whether ``module`` cannot be imported (not installed, or blocked), without importing it."""
    try:
        return importlib.util.find_spec(module) is None
    except (ImportError, ValueError, AttributeError):  # blocked (sys.modules[name] = None) or a broken parent
        return True


def check_extras(command: str, extras: Iterable[str]) -> None:
    """Raises :class:`MissingExtraError` for the first missing module of ``extras``.

    Args:
        command: the command line's command, for the message (``"info"``, ``"live --record"``).
        extras: names of :data:`EXTRAS`.
    """
    for extra in extras:
        for module, package in EXTRAS[extra]:
            if missing_module(module):
                pip = _PIP_EXTRA.get(extra, extra)
                raise MissingExtraError(f"'dmarionette {command}' needs the {package} package: "
                                        f"pip install -e '.[{pip}]' (in the source tree; or pip install "
                                        f"'dmarionette[{pip}]')")


def command_extras(args: argparse.Namespace) -> list[tuple[str, str]]:
    """The extras a parsed command line needs: ``(what needs it, extra)`` pairs, in the order checked."""
    command = getattr(args, "command", None)
    get = lambda name, default=None: getattr(args, name, default)  # noqa: E731
    needs: list[tuple[str, str]] = []
    if command in ("simulate", "demo"):
        if not get("no_picture", False):
            needs.append((command, "viz"))
            if get("animation") == "mp4":
                needs.append((f"{command} --animation mp4", "mp4"))
    elif command in ("info", "replay", "session"):
        needs.append((command, "io"))
    elif command == "live":
        devices = get("device") or []
        if get("record") is not None:
            needs.append(("live --record", "io"))
        if "replay" in devices or get("session") is not None:
            needs.append(("live --device replay", "io"))
        if get("view") == "browser":
            needs.append(("live --view browser", "view"))
        if get("snapshot") is not None:
            needs.append(("live --snapshot", "viz"))
        if "falcon" in devices:
            needs.append(("live --device falcon", "hw-falcon"))
        if "spacemouse" in devices:
            needs.append(("live --device spacemouse", "hw-spacemouse"))
    elif command == "bench":
        needs.append((command, "viz"))  # accuracy.png
    elif command == "export":
        if get("format") == "usd":
            needs.append(("export --format usd", "usd"))
    elif command == "sweep":
        if not get("no_picture", False):
            needs.append((command, "viz"))  # sweep.png
    elif command in ("author", "calibrate"):
        needs.append((command, "fitting"))
        if command == "author":
            needs.append((command, "viz"))  # animations and convergence.png
    if command in ("sweep", "author", "calibrate") and get("ray") not in (None, "off"):
        needs.append((f"{command} --ray {get('ray')}", "scale"))
    return [(what, extra) for what, extra in needs if extra in EXTRAS]


def check_command_extras(args: argparse.Namespace) -> None:
    """Raises :class:`MissingExtraError` (one line: the extra to install) if the command lacks one."""
    for what, extra in command_extras(args):
        check_extras(what, [extra])
