"""yauyau: the optimal nonlinear filter in real time (the Yau–Yau algorithm).

The repository keeps the three layers as top-level folders (``solver/`` the mathematics,
``storage/`` files and rows, ``service/`` HTTP and the CLI); installed, they are the subpackages
``yauyau.solver``, ``yauyau.storage`` and ``yauyau.service`` (pyproject.toml's ``package-dir``), and
nothing else is put at the top level of site-packages.
"""

from __future__ import annotations

from pathlib import Path as _Path

# In a source checkout this file sits in ``yauyau/`` beside ``solver/``, ``storage/`` and
# ``service/``: the checkout's root then serves as the rest of the package (so the tests, the
# benchmarks and ``PYTHONPATH=.`` run the working tree).  Installed, the subpackages are copied
# next to this file and nothing is added.
if not (_Path(__file__).resolve().parent / "solver").is_dir():
    __path__.append(str(_Path(__file__).resolve().parent.parent))  # noqa: F821 (a package's __path__)

__version__ = "0.2.0"
