"""examples/coupled_ring_4d.toml (method yau-niu) through the CLI a newcomer would type — precompute,
simulate, filter — against a 20 000-particle bootstrap filter of the ring written in the tests
(tests/helpers/ring.py): independent truth for the whole path, files and columns included."""

from __future__ import annotations

import csv

import numpy as np
from helpers import EXAMPLES
from helpers.ring import ring_bootstrap
from yauyau.service.cli import main


def test_the_ring_example_filters_through_the_cli_beside_a_particle_filter(tmp_path, capsys):
    spec, store, sim = EXAMPLES / "coupled_ring_4d.toml", tmp_path / "store", tmp_path / "sim"
    assert main(["precompute", str(spec), "--store", str(store), "--quiet"]) == 0
    model_id = capsys.readouterr().out.strip().splitlines()[-1]
    assert main(["simulate", str(spec), "--steps", "200", "--seed", "2", "--out", str(sim)]) == 0
    out = tmp_path / "est.csv"
    assert main(["filter", model_id, "--store", str(store), "--increments", str(sim / "increments.csv"),
                 "--out", str(out)]) == 0
    with out.open() as fh:
        table = list(csv.DictReader(fh))
    means = np.array([[float(r[f"mean_x{i}"]) for i in range(4)] for r in table])
    rows = np.loadtxt(sim / "increments.csv", delimiter=",", skiprows=1)  # dy_1 … dy_4
    particles = ring_bootstrap(rows, 20_000, seed=1)
    gap = float(np.sqrt(np.mean((means - particles) ** 2)))
    assert len(table) == 200 and gap < 0.06, gap
