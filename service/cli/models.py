"""`yauyau models --store DIR [--json]`: the stored models, from the HDF5 attributes only.

A table (id, name, n, m, dt, radius, domain, follow, basis, size, created; domain is "ball", or for
``[domain] shape`` "ellipsoid" (a covariance given) or "posterior" (the steady-state Kalman–Bucy one);
follow is "yes" for a domain that re-centres on the posterior, "region" for one confined to
``[domain] region``) or, with --json, a JSON list of the same fields (``shape`` for domain) plus
``region`` and ``error`` (set for a file that cannot be read).
"""

from __future__ import annotations

import argparse
import json

from .precompute import store_argument

_COLUMNS = ("id", "name", "n", "m", "dt", "radius", "domain", "follow", "basis", "size", "created")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    store_argument(parser)
    parser.add_argument("--json", action="store_true", help="print a JSON list instead of a table")


def _row(summary) -> list[str]:
    if summary.error:
        return [summary.id, f"unreadable: {summary.error}"] + [""] * (len(_COLUMNS) - 2)
    size = f"{summary.file_size / 1e6:.2f} MB"
    follow = "region" if summary.region else "yes" if summary.follow else "no"
    domain = "ball" if summary.shape is None else "posterior" if summary.shape == "posterior" else "ellipsoid"
    values = (summary.id, summary.name, summary.n, summary.m, summary.dt, summary.radius, domain, follow,
              summary.basis, size, summary.created)
    return ["" if v is None else str(v) for v in values]


def table(summaries) -> str:
    rows = [list(_COLUMNS)] + [_row(s) for s in summaries]
    widths = [max(len(r[i]) for r in rows) for i in range(len(_COLUMNS))]
    return "\n".join("  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip()
                     for r in rows)


def run(args: argparse.Namespace) -> int:
    from yauyau.storage.errors import StoreError
    from yauyau.storage.model_store import ModelStore

    store = ModelStore(args.store)
    if not store.directory.is_dir():
        raise StoreError("store", f"{store.directory} is not a directory")
    summaries = store.list()
    if args.json:
        print(json.dumps([s.to_dict() for s in summaries], indent=2))
    elif not summaries:
        print(f"no models in {store.directory}")
    else:
        print(table(summaries))
    return 0
