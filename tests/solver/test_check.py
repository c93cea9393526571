"""`yauyau check` (solver/check.py): a resolution check before any data arrives.

Truth: a 2-D linear model observed in both coordinates (the posterior is narrow), where basis 400 on
radius 6 is biased and degenerates while 900 is fine — measured here against the exact Kalman filter
on paths the check never saw.  The check must predict both, and the basis it suggests must pass on
those fresh paths too.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from helpers import EXAMPLES
from yauyau.service.cli import main
from yauyau.solver.check import CheckReport, Trial, coarser_than_measured, resolution_check
from yauyau.solver.errors import InputError
from yauyau.solver.reference.kalman import DiscreteKalmanFilter
from yauyau.solver.simulate import simulate
from yauyau.solver.spec import spec_from_dict

import yauyau

DOC = {"name": "linear-2d", "state": ["x1", "x2"], "drift": ["-0.5*x1 + x2", "-x1 - 0.5*x2"],
       "observation": ["x1", "x2"], "observation_noise": [[0.05, 0.0], [0.0, 0.05]],
       "initial": {"kind": "gaussian", "mean": [0.5, 0.0], "cov": [[1.0, 0.0], [0.0, 1.0]]},
       "domain": {"radius": 6.0}, "discretization": {"dt": 0.01, "basis": 400}}


def _spec(basis):
    return spec_from_dict({**DOC, "discretization": {"dt": 0.01, "basis": basis}})


def _against_kalman(basis, seeds=(101, 102, 103)):
    """(mean gap to the exact Kalman filter, degenerate steps) of the engine on fresh paths."""
    from yauyau.solver.check import _filter

    engine = _filter(_spec(basis), basis)
    kalman = DiscreteKalmanFilter(engine.model)
    gaps, bad = [], 0
    for seed in seeds:
        sim = simulate(engine.model, 300, np.random.default_rng(seed))
        _, result = engine.run_arrays(engine.initial_state(), sim.increments)
        _, ref = kalman.run(kalman.initial_state(), sim.increments)
        gaps.append(np.max(np.abs(result.mean - np.array([e.mean for e in ref])), axis=1))
        bad += int(result.degenerate.sum())
    return float(np.mean(np.concatenate(gaps))), bad


@pytest.mark.slow
def test_the_check_predicts_the_bias_at_400_and_suggests_a_basis_that_passes():
    report = resolution_check(_spec(400))
    low = report.requested
    assert not low.ok and low.degenerate > 0.1 and low.mean_gap > 0.1
    assert low.rmse > 1.5 * report.reference_rmse  # biased: far from what the optimal filter achieves
    assert "NOT RESOLVED" in report.render() and "Kalman" in report.reference
    suggested = report.suggested
    assert suggested is not None and 400 < suggested <= 1200
    # the truth, on paths the check never saw: 400 is off, the suggestion is not
    gap_400, bad_400 = _against_kalman(400)
    gap_suggested, bad_suggested = _against_kalman(suggested)
    assert gap_400 > 0.1 and bad_400 > 0
    assert gap_suggested <= report.target and bad_suggested == 0


@pytest.mark.slow
def test_the_check_passes_at_900_as_the_kalman_filter_says():
    report = resolution_check(_spec(900), suggest=True)
    assert report.requested.ok and len(report.trials) == 1 and report.suggested == 900
    gap, bad = _against_kalman(900)
    assert gap <= report.target and bad == 0


def test_the_cli_exit_status_says_resolved_or_not(tmp_path, capsys):
    import tomllib

    spec = EXAMPLES / "cubic_sensor.toml"
    assert tomllib.loads(spec.read_text())["discretization"]["basis"] == 128
    assert main(["check", str(spec), "--paths", "2", "--steps", "200"]) == 0  # nonlinear: against 2x basis
    out = capsys.readouterr().out
    assert "OK" in out and "basis 256" in out
    assert "reference: the engine at basis 256" in out and "truth" not in out  # a reference, not the truth
    with pytest.raises(InputError, match="paths"):
        resolution_check(_spec(400), paths=0)
    assert main(["check", str(spec), "--paths", "0"]) == 2


@pytest.mark.slow
def test_precompute_warns_when_the_exact_filter_shows_the_basis_is_too_small(tmp_path, capsys):
    import json

    for basis, warned in ((400, True), (900, False)):
        path = tmp_path / f"linear-{basis}.json"
        doc = {**DOC, "method": "yau-yau", "discretization": {"dt": 0.01, "basis": basis}}
        path.write_text(json.dumps(doc))
        assert main(["precompute", str(path), "--store", str(tmp_path / "store")]) == 0
        err = capsys.readouterr().err
        assert ("warning: basis 400 does not resolve" in err) is warned, err
        if warned:
            assert f"yauyau check {path}" in err


ATLAS = {"name": "sin drift", "state": ["x"], "drift": ["0.8 + 0.3*sin(x)"], "observation": ["x"],
         "method": "yau-yau", "initial": {"kind": "gaussian", "mean": [0.0], "cov": [[1.0]]},
         "domain": {"radius": 6.0, "follow": True, "region": [[-5.0, 60.0]]},
         "discretization": {"dt": 0.02, "basis": 4}}


@pytest.mark.slow
def test_a_reference_that_degenerates_is_refined_or_judges_nothing():
    """Basis 4 on the atlas: the engine at 8 degenerates on ~40% of the steps, so the reference is the
    engine at 16; a suggested basis is judged against twice its own (before, basis 12 'passed' against
    the degenerate basis 8, its gaps taken over the steps where 8 still worked).  From basis 2 the
    references 4 and 8 both degenerate: then nothing passes and nothing is suggested."""
    report = resolution_check(spec_from_dict(ATLAS), paths=2, steps=200)
    assert "basis 16" in report.reference and report.reference_degenerate == 0.0
    assert not report.requested.ok and report.suggested is not None
    passing = [t for t in report.trials if t.ok]
    assert passing and all(f"basis {2 * t.basis} " in (t.against or report.reference) for t in passing)
    coarse = resolution_check(spec_from_dict({**ATLAS, "discretization": {"dt": 0.02, "basis": 2}}),
                              paths=2, steps=200)
    assert "basis 8" in coarse.reference and coarse.reference_degenerate > 0.1
    assert coarse.suggested is None and len(coarse.trials) == 1
    assert "the reference itself degenerates" in coarse.render()


@pytest.mark.slow
def test_the_report_bounds_the_degenerate_rate_and_says_how_much_of_the_region_the_paths_crossed():
    """A pass on short paths is not a pass on a long run: with no degenerate step in n the report gives
    the rule of three's bound 3/n; on an atlas it says which part of domain.region the paths crossed
    (the drift 0.8 + 0.3 sin x carries x about 0.8·t: 200 steps of 0.02 cross ~3 of the region's 65)."""
    doc = {**ATLAS, "discretization": {"dt": 0.02, "basis": 24}}
    report = resolution_check(spec_from_dict(doc), paths=2, steps=200, suggest=False)
    assert report.requested.ok and report.requested.degenerate == 0.0
    assert report.rate_bound == pytest.approx(3.0 / 400)
    (lo, hi), = report.covered
    assert -5.0 < lo < 0.0 < hi < 12.0 and report.region == [[-5.0, 60.0]]
    text = report.render()
    assert "no degenerate step in 400: the rate is below 0.0075 per step" in text
    assert f"the paths crossed [{lo:.3g}, {hi:.3g}] of [-5, 60] of domain.region" in text
    assert "the centres beyond are not checked" in text
    assert report.to_dict()["covered"] == report.covered


def test_check_help_explains_the_report_and_the_exit_status(capsys):
    with pytest.raises(SystemExit) as done:
        main(["check", "-h"])
    assert done.value.code == 0
    out = capsys.readouterr().out
    for line in ("reference", "mean gap, largest", "degenerate steps", "RMSE (reference R)", "NOT RESOLVED",
                 "suggestion", "exit status: 0 resolved", "1 not resolved", "2 bad input"):
        assert line in out, line
    assert "truth" not in out


def test_the_json_report_names_its_reference():
    trial = Trial(basis=8, nodes=9, mean_gap=0.01, max_gap=0.02, degenerate=0.0, rmse=0.3, ok=True)
    report = CheckReport(reference="the exact Kalman filter (the model is linear)", target=0.05, paths=1,
                         steps=10, trials=[trial], reference_rmse=0.29)
    shown = report.to_dict()
    assert shown["reference"].startswith("the exact Kalman") and shown["reference_rmse"] == 0.29
    assert not [key for key in shown if "truth" in key]
    assert "reference: the exact Kalman" in report.render() and "truth" not in report.render()
# -- the rule `yauyau precompute` warns with before it solves (solver/defaults.py) ------------------------
LINEAR_3D = {"name": "linear-3d", "state": ["x1", "x2", "x3"], "method": "yau-yau",
             "drift": ["-x1 + 0.5*x2", "-x2", "-0.5*x3"], "observation": ["x1", "x3"],
             "initial": {"kind": "gaussian", "mean": [0.0, 0.0, 0.0],
                         "cov": [[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5]]},
             "domain": {"radius": 4.0}}
FOLLOWING = {"radius": 3.5, "follow": True}


def _coarse(domain=None, diffusion=None, **disc):
    doc = {**LINEAR_3D, "discretization": {"dt": 0.02, "basis": 500, **disc}}
    doc.update({"domain": domain} if domain else {}, **({"diffusion": diffusion} if diffusion else {}))
    return coarser_than_measured(spec_from_dict(doc))


def test_a_3d_mesh_measured_coarser_than_the_default_is_named_with_its_fix():
    """bench/results/default-3d.md: in 3-D P1 below the ball refined five times is farther from the exact
    filter than P2 + bubbles (fixed ball, basis 500: 2.3e-2 and 67% against 6.6e-3 and 21%), and on a
    following ball P2 + bubbles refined twice is farther than refined three times (6.8e-3 and 9.7%
    against 3.8e-3 and 4.1%).  The defaults, and P1 refined five times, are not warned about."""
    assert _coarse() is None and _coarse(FOLLOWING) is None  # the plain specs
    assert _coarse(element="bubble", mesh=2) is None  # a fixed ball: no closer refined three times
    assert _coarse(FOLLOWING, element="bubble", mesh=3) is None
    assert _coarse(FOLLOWING, element="lagrange", mesh=5) is None
    field, message = _coarse(element="lagrange")
    assert field == "discretization.element" and message.startswith("P1 on 4991 mesh nodes is measured")
    assert "leave mesh and element out (P2 + bubbles) or set mesh = 5" in message
    assert "yauyau check" in message
    assert _coarse(mesh=4)[0] == "discretization.mesh"  # a mesh set: P1 on it
    field, message = _coarse(order=1)
    assert field == "discretization.order" and "with order = 2" in message
    field, message = _coarse(FOLLOWING, element="bubble", mesh=2)
    assert field == "discretization.mesh" and message.startswith("P2 + bubbles on 2047 mesh nodes")
    assert "set mesh = 3" in message
    # noise on two coordinates: SUPG, built on P1, so the fix is P1's finer ball
    field, message = _coarse(diffusion=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    assert field == "discretization.mesh" and "set mesh = 5 (41727 nodes)" in message
    # 1-D and 2-D have no such rule (their defaults: bench/results/default-mesh.md), nor a mesh-free method
    assert coarser_than_measured(_spec(400)) is None
    assert coarser_than_measured(spec_from_dict({**LINEAR_3D, "method": "kalman-bucy",
                                                 "discretization": {"dt": 0.02, "basis": 8}})) is None


def test_precompute_warns_on_a_coarse_3d_mesh_before_it_solves(tmp_path, capsys):
    path = tmp_path / "coarse-3d.json"
    path.write_text(json.dumps({**LINEAR_3D, "discretization": {"dt": 0.02, "basis": 8, "mesh": 2,
                                                                 "order": 1}}))
    assert main(["precompute", str(path), "--store", str(tmp_path / "store"), "--workers", "1"]) == 0
    err = capsys.readouterr().err
    [line] = [row for row in err.splitlines() if "63 mesh nodes" in row]
    assert line.startswith("yauyau precompute: warning: discretization.mesh: P1 on 63 mesh nodes is "
                           "measured farther"), err
    with pytest.warns(UserWarning, match=r"discretization\.mesh: P1 on 63 mesh nodes"):
        yauyau.precompute(str(path), tmp_path / "api-store")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a spec of another dimension: no warning
        plain_2d = {**DOC, "method": "yau-yau", "discretization": {"dt": 0.01, "basis": 8}}
        yauyau.precompute(spec_from_dict(plain_2d), tmp_path / "api-store")
