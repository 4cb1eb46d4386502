"""``dsg-view``: a world in the browser, with the ``DSGWorldEnv`` behind the page (docs/viewer.md).

:class:`~dsg_gym.viewer.server.Viewer` serves the page (needs the ``viewer`` extra, viser);
:class:`~dsg_gym.viewer.env_state.ViewerSession` is the env-side state it drives and works without viser.
Importing this package imports neither viser nor the renderer."""

from __future__ import annotations

from typing import TYPE_CHECKING

__all__ = ["Verdict", "Viewer", "ViewerSession"]

if TYPE_CHECKING:
    from .env_state import Verdict, ViewerSession
    from .server import Viewer


def __getattr__(name: str):
    if name == "Viewer":
        from .server import Viewer

        return Viewer
    if name in ("Verdict", "ViewerSession"):
        from . import session

        return getattr(session, name)
    raise AttributeError(f"module 'dsg_gym.viewer' has no attribute {name!r}")
