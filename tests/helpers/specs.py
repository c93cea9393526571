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
