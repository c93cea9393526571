"""Spec documents for the tests: a base document with some of its tables changed."""

from __future__ import annotations

import json


def modified(base: dict, **changes) -> dict:
    """A deep copy of ``base`` with each change applied: a dict updates that table, anything else
    replaces the key."""
    doc = json.loads(json.dumps(base))
    for key, value in changes.items():
        if isinstance(value, dict):
            doc.setdefault(key, {}).update(value)
        else:
            doc[key] = value
    return doc


def dos_spec(exponent: int) -> dict:
    """The 3-D spec of the attack: h = (x + y + z + 1)**e on a tiny ball (SymPy's expand of h² blew up)."""
    eye = [[1e-6 if i == j else 0.0 for j in range(3)] for i in range(3)]
    return {"name": "dos", "state": ["x", "y", "z"], "drift": ["-x", "-y", "-z"],
            "observation": [f"(x+y+z+1)**{exponent}"],
            "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0], "cov": eye},
            "domain": {"radius": 0.01}, "discretization": {"dt": 0.01, "basis": 8}}
