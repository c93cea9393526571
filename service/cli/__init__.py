"""The ``yauyau`` console script (:func:`main`) and its subcommands, one module each.

``service/cli/<name>.py`` holds ``add_arguments(parser)`` and ``run(args) -> int``; ``main.py`` parses
and dispatches; ``python -m yauyau.service.cli`` runs it too.
"""

from .main import main

__all__ = ["main"]
