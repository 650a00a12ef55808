"""A run replayed in 3-D in the browser (``cochlea-view``, docs/logs.md): the run's frames as
JSON (:mod:`cochlea.view.replay`, read through :mod:`cochlea.export.run_log`) and one
self-contained HTML page that draws them (:mod:`cochlea.view.page`)."""

from .page import render_page
from .replay import DEFAULT_RATE_HZ, build_replay

__all__ = ["build_replay", "render_page", "DEFAULT_RATE_HZ"]
