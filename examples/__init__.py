"""The example model specs, shipped with the package: ``yauyau.examples.path("cubic_sensor")``.

    import yauyau

    spec = yauyau.load_spec(yauyau.examples.path("cubic_sensor"))
    yauyau.examples.names()        # ['benes', 'constant_velocity', 'cubic_sensor', ...]

The repository keeps them in ``examples/`` at its top (beside ``solver/``, ``storage/``, ``service/``);
installed, that folder is the package ``yauyau.examples`` (pyproject.toml's ``package-dir``, the
``*.toml`` files as package data), so a spec is found from any directory after ``pip install``.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from yauyau.solver.errors import SpecError

SUFFIX = ".toml"


def names() -> list[str]:
    """The examples' names, sorted: their file names without ``.toml``."""
    found = (item.name for item in files(__name__).iterdir())
    return sorted(name[:-len(SUFFIX)] for name in found if name.endswith(SUFFIX))


def path(name: str) -> Path:
    """The spec file of the example ``name`` ("cubic_sensor"; "cubic_sensor.toml" will do); an unknown
    name raises SpecError('example') naming the examples there are."""
    known = names()
    stem = name[:-len(SUFFIX)] if isinstance(name, str) and name.endswith(SUFFIX) else name
    if stem not in known:
        raise SpecError("example", f"no example named {name!r}; the examples are: {', '.join(known)}")
    # installed from a wheel or run from a checkout, the package is a folder: its files are real paths
    return Path(str(files(__name__) / f"{stem}{SUFFIX}"))
